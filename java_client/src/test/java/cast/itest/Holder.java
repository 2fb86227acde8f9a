package cast.itest;

import cast.client.AlreadyExistsError;
import cast.client.LockMode;
import cast.client.ManagedComponent;
import cast.client.Task;
import cast.testing.CastTesting.Counter;
import java.time.Duration;

/**
 * Holds an ODR lock on entry "held" and an adopted task "hold" for as long as it
 * lives: the orchestrator test kills it with SIGKILL and checks that both are
 * released and that it is restarted (the restarted one takes them again).
 */
public class Holder extends ManagedComponent {
  @Override
  public void start() {
    try {
      add("held", Counter.newBuilder().setWriter(componentId()).build());
    } catch (AlreadyExistsError e) {
      // a restart: the entry outlives the component
    }
    lock("held", LockMode.ODR, Duration.ofSeconds(60));
    proposeTask("hold");
    log().info("holding the lock on 'held'");
  }

  @Override
  public void taskAdopted(Task task) {
    log().info("adopted " + task);
  }
}
