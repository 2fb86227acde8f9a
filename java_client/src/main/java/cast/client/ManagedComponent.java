package cast.client;

import com.google.protobuf.Message;

/**
 * A component whose expensive work runs as tasks that its SA's task manager
 * adopts: propose a task, do the work in {@link #taskAdopted}, then report it
 * with {@link #taskComplete}.
 */
public abstract class ManagedComponent extends Component {
  @Override
  final String kind() {
    return "managed";
  }

  @Override
  void bindExtra(Transport transport) {
    transport.openDecisions(this::onDecision);
  }

  private void onDecision(Task task) {
    switch (task.state()) {
      case ADOPTED:
        submit(() -> taskAdopted(task));
        break;
      case REJECTED:
        submit(() -> taskRejected(task));
        break;
      default:
        break; // other states are not decisions a component acts on
    }
  }

  /** Propose a task without data to the own SA's task manager; the decision arrives in a hook. */
  public Task proposeTask(String name) {
    return proposeTask(name, null, 0);
  }

  /** Propose a task with a payload the policy and the hooks can read. */
  public Task proposeTask(String name, Message data) {
    return proposeTask(name, data, 0);
  }

  /** Propose a task with a payload and a priority (higher runs first under the priority policy). */
  public Task proposeTask(String name, Message data, int priority) {
    if (name == null || name.isEmpty()) {
      throw new InvalidArgumentError("a task needs a name");
    }
    return transport().propose(name, data == null ? null : serialise(data, null), priority);
  }

  /** Withdraw a waiting or adopted task. */
  public void retractTask(Task task) {
    retractTask(task.taskId());
  }

  /** Withdraw a waiting or adopted task by id. */
  public void retractTask(String taskId) {
    transport().retract(taskId);
  }

  /** Report that an adopted task succeeded. */
  public void taskComplete(Task task) {
    taskComplete(task.taskId(), TaskOutcome.SUCCEEDED, "");
  }

  /** Report that an adopted task ended with {@code outcome}. */
  public void taskComplete(Task task, TaskOutcome outcome) {
    taskComplete(task.taskId(), outcome, "");
  }

  /** Report that an adopted task ended with {@code outcome}, and why. */
  public void taskComplete(Task task, TaskOutcome outcome, String reason) {
    taskComplete(task.taskId(), outcome, reason);
  }

  /** Report that an adopted task (by id) ended with {@code outcome}, and why. */
  public void taskComplete(String taskId, TaskOutcome outcome, String reason) {
    transport().complete(taskId, outcome == null ? TaskOutcome.SUCCEEDED : outcome, reason);
  }

  /** Hook: the task manager adopted {@code task}; do the work, then call taskComplete. */
  public void taskAdopted(Task task) throws Exception {}

  /** Hook: the task manager rejected {@code task}. */
  public void taskRejected(Task task) throws Exception {}
}
