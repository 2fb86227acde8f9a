package cast.client;

import com.google.protobuf.Any;
import com.google.protobuf.Message;

/** A task proposed by a managed component, as its task manager decided. */
public final class Task {
  private final String taskId;
  private final String name;
  private final String subarchitecture;
  private final String component;
  private final int priority;
  private final TaskState state;
  private final String reason;
  private final Any data; // null: proposed without data

  Task(
      String taskId,
      String name,
      String subarchitecture,
      String component,
      int priority,
      TaskState state,
      String reason,
      Any data) {
    this.taskId = taskId;
    this.name = name;
    this.subarchitecture = subarchitecture;
    this.component = component;
    this.priority = priority;
    this.state = state;
    this.reason = reason;
    this.data = data;
  }

  /** Id given by the task manager. */
  public String taskId() {
    return taskId;
  }

  /** Name given at proposal. */
  public String name() {
    return name;
  }

  /** The SA whose task manager decided. */
  public String subarchitecture() {
    return subarchitecture;
  }

  /** Id of the proposing component. */
  public String component() {
    return component;
  }

  /** Priority given at proposal. */
  public int priority() {
    return priority;
  }

  /** WAITING, ADOPTED, REJECTED, ... */
  public TaskState state() {
    return state;
  }

  /** Why the task was rejected, retracted or ended. */
  public String reason() {
    return reason;
  }

  /** Whether the proposal carried a payload. */
  public boolean hasData() {
    return data != null && !data.getTypeUrl().isEmpty();
  }

  /** The proposal's payload as {@code cls}, or null if it had none. */
  public <T extends Message> T data(Class<T> cls) {
    if (!hasData()) {
      return null;
    }
    return Types.decode(
        cls,
        Types.typeOf(data),
        data.getValue(),
        "task '" + taskId + "' data",
        subarchitecture,
        "it was proposed corrupt or with another schema; complete or retract the task");
  }

  @Override
  public String toString() {
    return "Task(" + taskId + " '" + name + "' " + state + ")";
  }
}
