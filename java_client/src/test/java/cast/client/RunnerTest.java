package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import java.time.Duration;
import java.util.ArrayList;
import java.util.HashMap;
import java.util.List;
import java.util.Map;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicInteger;
import org.junit.jupiter.api.Test;

class RunnerTest {
  public static final class Good extends UnmanagedComponent {}

  public abstract static class Abstract extends UnmanagedComponent {}

  /** Stops as soon as run() begins. */
  public static final class Quick extends UnmanagedComponent {
    @Override
    public void run() {
      requestStop();
    }
  }

  public static final class NoDefaultConstructor extends UnmanagedComponent {
    public NoDefaultConstructor(int x) {}
  }

  @Test
  void loadsComponentClassesByName() {
    assertEquals(Good.class, Runner.loadComponentClass(Good.class.getName()));
  }

  @Test
  void explainsWhatIsWrongWithAClassName() {
    InvalidArgumentError missing =
        assertThrows(InvalidArgumentError.class, () -> Runner.loadComponentClass("no.such.Component"));
    assertTrue(missing.getMessage().contains("not on the class path"), missing.getMessage());
    InvalidArgumentError notComponent =
        assertThrows(InvalidArgumentError.class, () -> Runner.loadComponentClass("java.lang.String"));
    assertTrue(notComponent.getMessage().contains("must extend cast.client.UnmanagedComponent"));
    assertThrows(InvalidArgumentError.class, () -> Runner.loadComponentClass(Abstract.class.getName()));
  }

  @Test
  void badCommandLinesAndEnvironmentsExitWith2() {
    Map<String, String> env = new HashMap<>();
    assertEquals(2, Runner.run(new String[] {}, env, false));
    assertEquals(2, Runner.run(new String[] {"a", "b"}, env, false));
    assertEquals(2, Runner.run(new String[] {"--help"}, env, false));
    assertEquals(2, Runner.run(new String[] {Good.class.getName()}, env, false), "no launch environment");
    assertEquals(2, Runner.run(new String[] {"no.such.Component"}, ArgsAndContractTest.env("{}"), false));
    assertEquals(
        2, Runner.run(new String[] {NoDefaultConstructor.class.getName()}, ArgsAndContractTest.env("{}"), false));
    assertEquals(2, Runner.run(new String[] {Good.class.getName()}, ArgsAndContractTest.env("[1]"), false));
  }

  @Test
  void anUnreachableSystemExitsWith2() {
    Map<String, String> env = ArgsAndContractTest.env("{}");
    // Port 1 on loopback: nothing listens there, the connection is refused at once. An empty
    // connect window gives up after the first refusal (ConnectWindowTest covers the asking).
    env.put("CAST_ENDPOINT", "127.0.0.1:1");
    ConnectWindow none = new ConnectWindow(Duration.ZERO, ConnectWindow.SYSTEM);
    assertEquals(2, Runner.run(new String[] {Good.class.getName()}, env, false, GrpcTransport::new, none));
    env.put("CAST_ENDPOINT", "not a valid:target:%%");
    assertEquals(2, Runner.run(new String[] {Good.class.getName()}, env, false));
  }

  static final class Lifecycle extends UnmanagedComponent {
    final StringBuilder calls = new StringBuilder();
    final boolean failInRun;

    Lifecycle(boolean failInRun) {
      this.failInRun = failInRun;
    }

    @Override
    public void configure(Args args) {
      calls.append("configure(").append(args.getInt("n", 0)).append(") ");
    }

    @Override
    public void start() {
      calls.append("start ");
    }

    @Override
    public void run() {
      calls.append("run ");
      if (failInRun) {
        throw new IllegalStateException("run failed on purpose");
      }
      requestStop();
    }

    @Override
    public void stop() {
      calls.append("stop");
    }
  }

  @Test
  void runComponentCallsTheHooksInOrderAndStopOnce() {
    FakeTransport.Memory memory = new FakeTransport.Memory("vision");
    Lifecycle ok = FakeTransport.connect(new Lifecycle(false), memory, "ok", "vision");
    FakeTransport okSession = FakeTransport.of(ok);
    assertEquals(0, Runner.runComponent(ok, Args.fromJson("{\"n\": 4}"), false));
    assertEquals("configure(4) start run stop", ok.calls.toString());
    // RUNNING once start() returned, STOPPING when stop() is called, each reported at once.
    assertEquals(List.of(ComponentState.RUNNING, ComponentState.STOPPING), okSession.reported);
    Lifecycle bad = FakeTransport.connect(new Lifecycle(true), memory, "bad", "vision");
    FakeTransport badSession = FakeTransport.of(bad);
    assertEquals(1, Runner.runComponent(bad, Args.empty(), false));
    assertEquals("configure(0) start run stop", bad.calls.toString());
    // Both sessions ended when the runner closed the components.
    assertTrue(okSession.closed && badSession.closed);
  }

  /** Fails in start(). */
  static final class FailsInStart extends UnmanagedComponent {
    @Override
    public void start() {
      throw new IllegalStateException("no camera attached");
    }
  }

  @Test
  void onStartedComesOnceBeforeRunAndAlsoWhenTheLifecycleEndsBeforeRun() {
    FakeTransport.Memory memory = new FakeTransport.Memory("vision");
    Lifecycle ok = FakeTransport.connect(new Lifecycle(false), memory, "ok", "vision");
    List<String> seen = new ArrayList<>();
    assertEquals(0, Runner.runComponent(ok, Args.empty(), false, false, () -> seen.add("started after " + ok.calls)));
    assertEquals(List.of("started after configure(0) start "), seen);
    FailsInStart failing = FakeTransport.connect(new FailsInStart(), memory, "failing", "vision");
    AtomicInteger called = new AtomicInteger();
    assertEquals(1, Runner.runComponent(failing, Args.empty(), false, false, called::incrementAndGet));
    assertEquals(1, called.get(), "a waiter for start() would wait for ever");
  }

  /** Run {@code c} (start barrier on) on a thread; its exit status lands in {@code status}. */
  private static Thread runWithBarrier(Component c, AtomicInteger status) {
    Thread t = new Thread(() -> status.set(Runner.runComponent(c, Args.empty(), false, true)), "barrier-test");
    t.start();
    return t;
  }

  @Test
  void withTheBarrierHeldRunWaitsForItsReleaseAndStartedIsReportedFirst() throws Exception {
    FakeTransport.Memory memory = new FakeTransport.Memory("vision");
    Lifecycle c = FakeTransport.connect(new Lifecycle(false), memory, "c", "vision");
    FakeTransport fake = FakeTransport.of(c).holdBarrier();
    AtomicInteger status = new AtomicInteger(-1);
    Thread t = runWithBarrier(c, status);
    assertTrue(fake.awaiting.await(5, TimeUnit.SECONDS), "awaitRun was called");
    Thread.sleep(300);
    assertEquals("configure(0) start ", c.calls.toString(), "run() waits while the barrier is held");
    // STARTED was reported (at once) before the wait, and was the state while waiting.
    assertEquals(List.of(ComponentState.STARTED), fake.reported);
    assertEquals(List.of(ComponentState.STARTED), fake.awaits);
    fake.releaseBarrier();
    t.join(10_000);
    assertFalse(t.isAlive());
    assertEquals(0, status.get());
    assertEquals("configure(0) start run stop", c.calls.toString());
    assertEquals(List.of(ComponentState.STARTED, ComponentState.RUNNING, ComponentState.STOPPING), fake.reported);
  }

  @Test
  void aStopRequestDuringTheWaitSkipsRunAndCallsStopOnce() throws Exception {
    FakeTransport.Memory memory = new FakeTransport.Memory("vision");
    Lifecycle c = FakeTransport.connect(new Lifecycle(false), memory, "c", "vision");
    FakeTransport fake = FakeTransport.of(c).holdBarrier();
    AtomicInteger status = new AtomicInteger(-1);
    Thread t = runWithBarrier(c, status);
    assertTrue(fake.awaiting.await(5, TimeUnit.SECONDS), "awaitRun was called");
    c.requestStop(); // as SIGTERM does
    t.join(10_000);
    assertFalse(t.isAlive());
    assertEquals(0, status.get(), "a clean stop");
    assertEquals("configure(0) start stop", c.calls.toString(), "run() never ran; stop() once");
    assertEquals(List.of(ComponentState.STARTED, ComponentState.STOPPING), fake.reported);
    assertTrue(fake.closed);
  }

  @Test
  void theLaunchEnvironmentSaysWhetherToWaitAtTheBarrier() {
    for (boolean barrier : new boolean[] {false, true}) {
      Map<String, String> env = ArgsAndContractTest.env("{}");
      if (barrier) {
        env.put("CAST_START_BARRIER", "1");
      }
      FakeTransport.Memory memory = new FakeTransport.Memory("vision");
      List<FakeTransport> made = new ArrayList<>();
      int status =
          Runner.run(new String[] {Quick.class.getName()}, env, false, contract -> {
            FakeTransport f = new FakeTransport(memory, new Identity("c1", "vision", false));
            made.add(f);
            return f;
          });
      assertEquals(0, status);
      FakeTransport fake = made.get(0);
      if (barrier) {
        assertEquals(List.of(ComponentState.STARTED), fake.awaits, "awaitRun called once, after STARTED");
        assertEquals(List.of(ComponentState.STARTED, ComponentState.RUNNING, ComponentState.STOPPING), fake.reported);
      } else {
        assertEquals(List.of(), fake.awaits, "without CAST_START_BARRIER awaitRun is never called");
        assertEquals(List.of(ComponentState.RUNNING, ComponentState.STOPPING), fake.reported);
      }
    }
  }

  @Test
  void aFailingBarrierFailsTheStartLikeAFailingHook() {
    FakeTransport.Memory memory = new FakeTransport.Memory("vision");
    Lifecycle c = FakeTransport.connect(new Lifecycle(false), memory, "c", "vision");
    FakeTransport.of(c).failBarrier(new PermissionDeniedError("no"));
    assertEquals(1, Runner.runComponent(c, Args.empty(), false, true));
    assertEquals("configure(0) start stop", c.calls.toString());
  }
}
