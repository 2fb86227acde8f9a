package cast.testing;

import cast.client.Args;
import cast.client.Component;
import cast.client.Runner;
import java.time.Duration;
import java.util.OptionalInt;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.TimeUnit;

/**
 * A component under test running its lifecycle on a thread of its own, as {@code
 * cast.client.Runner} runs it: configure(args), start(), run(); stop() once at the end. {@link
 * LocalSystem#run} hands it over once start() returned, so its watches are registered.
 *
 * @param <C> the component's class
 */
public final class RunningComponent<C extends Component> {
  private final C component;
  private final String componentId;
  private final CountDownLatch started = new CountDownLatch(1);
  private final CountDownLatch ended = new CountDownLatch(1);
  private final Thread thread;
  private volatile Integer exitCode;

  RunningComponent(C component, Args args) {
    this.component = component;
    this.componentId = component.componentId();
    this.thread =
        new Thread(
            () -> {
              try {
                exitCode = Runner.runComponent(component, args, false, false, started::countDown);
              } finally {
                if (exitCode == null) {
                  exitCode = 1;
                }
                started.countDown();
                ended.countDown();
              }
            },
            "cast-testing-" + componentId);
    thread.setDaemon(true);
    thread.start();
  }

  void awaitStarted(Duration timeout) {
    try {
      if (!started.await(timeout.toMillis(), TimeUnit.MILLISECONDS)) {
        throw new AssertionError(componentId + ": start() did not return within " + CastTesting.seconds(timeout)
            + " s");
      }
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
      throw new AssertionError("interrupted while " + componentId + " started", e);
    }
  }

  /** The component object (its fields are the test's to read). */
  public C component() {
    return component;
  }

  /** The component's id. */
  public String componentId() {
    return componentId;
  }

  /** Whether its lifecycle is still going. */
  public boolean isRunning() {
    return ended.getCount() > 0;
  }

  /** 0 after a clean stop, 1 when a hook threw; empty while it runs. */
  public OptionalInt exitCode() {
    Integer code = isRunning() ? null : exitCode;
    return code == null ? OptionalInt.empty() : OptionalInt.of(code);
  }

  /** {@link #join(Duration)} for 10 s. */
  public int join() {
    return join(CastTesting.DEFAULT_TIMEOUT);
  }

  /**
   * Waits until the component stops by itself (requestStop(), a hook that threw); its exit code.
   * AssertionError after {@code timeout}.
   */
  public int join(Duration timeout) {
    try {
      if (!ended.await(timeout.toMillis(), TimeUnit.MILLISECONDS)) {
        throw new AssertionError(componentId + " did not stop by itself within " + CastTesting.seconds(timeout) + " s");
      }
      thread.join();
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
      throw new AssertionError("interrupted while waiting for " + componentId + " to stop", e);
    }
    return exitCode;
  }

  /** {@link #stop(Duration)} for 10 s. */
  public int stop() {
    return stop(CastTesting.DEFAULT_TIMEOUT);
  }

  /**
   * Asks the component to stop and waits for its end; its exit code (assert it, so that a
   * component that failed quietly fails the test).
   */
  public int stop(Duration timeout) {
    if (isRunning()) {
      component.requestStop();
    }
    // The runner gives run() 10 s and the queued callbacks 5 s after the request.
    return join(timeout.plusSeconds(15));
  }
}
