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
  COMPLETED;

  /** The state of a wire value. */
  public static TaskState fromProto(cast.v1.TaskState state) {
    switch (state) {
      case TASK_STATE_WAITING:
        return WAITING;
      case TASK_STATE_ADOPTED:
        return ADOPTED;
      case TASK_STATE_REJECTED:
        return REJECTED;
      case TASK_STATE_RETRACTED:
        return RETRACTED;
      case TASK_STATE_COMPLETED:
        return COMPLETED;
      default:
        return UNSPECIFIED;
    }
  }
}
