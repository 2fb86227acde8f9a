package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import java.util.HashMap;
import java.util.List;
import java.util.Map;
import org.junit.jupiter.api.Test;

class RunnerTest {
  public static final class Good extends UnmanagedComponent {}

  public abstract static class Abstract extends UnmanagedComponent {}

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
    // Port 1 on loopback: nothing listens there, the connection is refused at once.
    env.put("CAST_ENDPOINT", "127.0.0.1:1");
    assertEquals(2, Runner.run(new String[] {Good.class.getName()}, env, false));
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
}
