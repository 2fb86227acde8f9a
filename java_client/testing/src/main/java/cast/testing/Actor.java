package cast.testing;

import cast.client.ManagedComponent;
import cast.client.Task;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;

/**
 * The test acting as a component ({@link LocalSystem#actAs}): every call of a component with that
 * component's identity and rights, and tasks, whose decisions it keeps.
 */
public final class Actor extends ManagedComponent {
  private final List<Task> decided = new ArrayList<>();

  /** Made by {@link LocalSystem#actAs}. */
  Actor() {}

  @Override
  public void taskAdopted(Task task) {
    synchronized (decided) {
      decided.add(task);
    }
  }

  @Override
  public void taskRejected(Task task) {
    synchronized (decided) {
      decided.add(task);
    }
  }

  /** The decisions about its tasks so far (adopted or rejected), in the order they came. */
  public List<Task> decisions() {
    synchronized (decided) {
      return List.copyOf(decided);
    }
  }

  /** The task as its task manager decided it; AssertionError after 10 s. */
  public Task waitForDecision(Task task) {
    return waitForDecision(task, CastTesting.DEFAULT_TIMEOUT);
  }

  /** The task as its task manager decided it; AssertionError after {@code timeout}. */
  public Task waitForDecision(Task task, Duration timeout) {
    Task[] found = new Task[1];
    CastTesting.waitFor(
        () -> {
          for (Task t : decisions()) {
            if (t.taskId().equals(task.taskId())) {
              found[0] = t;
              return true;
            }
          }
          return false;
        },
        timeout,
        "the decision about task " + task.taskId() + " of " + componentId(),
        () -> "decisions so far: " + decisions());
    return found[0];
  }
}
