package cast.client;

import com.google.protobuf.Message;

/** A task proposed by a managed component, as its task manager decided. */
public final class Task {
  private final cast.v1.Task task;

  Task(cast.v1.Task task) {
    this.task = task;
  }

  /** Id given by the task manager. */
  public String taskId() {
    return task.getTaskId();
  }

  /** Name given at proposal. */
  public String name() {
    return task.getName();
  }

  /** The SA whose task manager decided. */
  public String subarchitecture() {
    return task.getSubarchitecture();
  }

  /** Id of the proposing component. */
  public String component() {
    return task.getComponent();
  }

  /** Priority given at proposal. */
  public int priority() {
    return task.getPriority();
  }

  /** WAITING, ADOPTED, REJECTED, ... */
  public TaskState state() {
    return TaskState.fromProto(task.getState());
  }

  /** Why the task was rejected, retracted or ended. */
  public String reason() {
    return task.getReason();
  }

  /** Whether the proposal carried a payload. */
  public boolean hasData() {
    return task.hasData() && !task.getData().getTypeUrl().isEmpty();
  }

  /** The proposal's payload as {@code cls}, or null if it had none. */
  public <T extends Message> T data(Class<T> cls) {
    if (!hasData()) {
      return null;
    }
    return Types.decode(
        cls,
        Types.typeOf(task.getData()),
        task.getData().getValue(),
        "task '" + taskId() + "' data",
        subarchitecture(),
        "it was proposed corrupt or with another schema; complete or retract the task");
  }

  /** The wire record. */
  public cast.v1.Task toProto() {
    return task;
  }

  @Override
  public String toString() {
    return "Task(" + taskId() + " '" + name() + "' " + state() + ")";
  }
}
