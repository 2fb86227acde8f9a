package cast.client;

/** Where a task is in its life. */
public enum TaskState {
  /** Not set (never sent by the server). */
  UNSPECIFIED,
  /** Proposed, not yet decided. */
  WAITING,
  /** The component may run it. */
  ADOPTED,
  /** The task manager refused it. */
  REJECTED,
  /** The proposer withdrew it (or its session ended). */
  RETRACTED,
  /** The proposer reported an outcome. */
  COMPLETED
}
