package cast.itest;

import static cast.client.Filters.localTypeFilter;

import cast.client.ManagedComponent;
import cast.client.Operation;
import cast.client.Task;
import cast.client.WorkingMemoryChange;
import cast.testing.CastTesting.Counter;

/**
 * Answers every Counter another component adds with a task that writes
 * "echo-&lt;id&gt;" (value + 1): each answer needs several calls (propose, add,
 * complete), made whenever a test writes, for instance after the component's
 * first token expired.
 */
public class Echo extends ManagedComponent {
  @Override
  public void start() {
    onChange(localTypeFilter(Counter.class, Operation.ADD).withEntry(), this::added);
  }

  private void added(WorkingMemoryChange change) {
    if (!change.sourceComponent().equals(componentId())) {
      Counter c = change.entry(Counter.class).value();
      proposeTask("echo", c.toBuilder().setWriter(change.id()).build());
    }
  }

  @Override
  public void taskAdopted(Task task) {
    Counter c = task.data(Counter.class);
    add("echo-" + c.getWriter(), Counter.newBuilder().setWriter(componentId()).setValue(c.getValue() + 1).build());
    taskComplete(task);
    log().info("echoed " + c.getWriter());
  }
}
