package cast.examples;

import static cast.client.Filters.localTypeFilter;

import cast.client.Args;
import cast.client.ManagedComponent;
import cast.client.Operation;
import cast.client.Task;
import cast.client.WorkingMemoryChange;

/** Answers every greeting added to its subarchitecture, as a task its task manager adopts. */
public class MyComponent extends ManagedComponent {
  private String prefix;

  @Override
  public void configure(Args args) {
    prefix = args.getString("prefix", "hello, ");
  }

  @Override
  public void start() {
    // Callbacks run on the component's dispatcher thread, one at a time, in revision order.
    onChange(localTypeFilter(Greeting.class, Operation.ADD).withEntry(), this::greeted);
  }

  private void greeted(WorkingMemoryChange change) {
    if (change.sourceComponent().equals(componentId())) {
      return; // our own answers
    }
    Greeting greeting = change.entry(Greeting.class).value();
    // Answering is the expensive part: ask the task manager first.
    proposeTask("answer", greeting.toBuilder().setReplyTo(change.id()).build());
  }

  @Override
  public void taskAdopted(Task task) {
    Greeting greeting = task.data(Greeting.class);
    Greeting answer =
        Greeting.newBuilder()
            .setText(prefix + greeting.getText())
            .setFrom(componentId())
            .setReplyTo(greeting.getReplyTo())
            .build();
    add("reply-" + greeting.getReplyTo(), answer);
    taskComplete(task);
  }
}
