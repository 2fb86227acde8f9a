package cast.client;

/** What a managed component reports when an adopted task ends. */
public enum TaskOutcome {
  /** The task did what it set out to do. */
  SUCCEEDED(cast.v1.TaskOutcome.TASK_OUTCOME_SUCCEEDED),
  /** The task ran and failed. */
  FAILED(cast.v1.TaskOutcome.TASK_OUTCOME_FAILED),
  /** The task was given up. */
  ABANDONED(cast.v1.TaskOutcome.TASK_OUTCOME_ABANDONED);

  private final cast.v1.TaskOutcome wire;

  TaskOutcome(cast.v1.TaskOutcome wire) {
    this.wire = wire;
  }

  /** The wire value. */
  public cast.v1.TaskOutcome toProto() {
    return wire;
  }
}
