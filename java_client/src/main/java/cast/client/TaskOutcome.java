package cast.client;

/** What a managed component reports when an adopted task ends. */
public enum TaskOutcome {
  /** The task did what it set out to do. */
  SUCCEEDED,
  /** The task ran and failed. */
  FAILED,
  /** The task was given up. */
  ABANDONED
}
