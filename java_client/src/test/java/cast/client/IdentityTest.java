package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import java.io.ByteArrayOutputStream;
import java.io.PrintStream;
import java.nio.charset.StandardCharsets;
import java.util.ArrayList;
import java.util.List;
import java.util.Map;
import org.junit.jupiter.api.Test;

/**
 * Who a component is comes from the server's answer to Register (the identity it
 * verified from the token), never from decoding the token; a launch environment or
 * connect options that say otherwise are refused at start, naming both. Against a real
 * server: tests/interop/test_java_identity.py.
 */
class IdentityTest {
  /** Records what the runner called; stops at once. */
  public static final class Recorder extends UnmanagedComponent {
    static final List<String> SEEN = new ArrayList<>();

    @Override
    public void start() {
      SEEN.add(componentId() + "@" + subarchitecture() + (isPrivileged() ? " privileged" : ""));
    }

    @Override
    public void run() {
      requestStop();
    }
  }

  final FakeTransport.Memory memory = new FakeTransport.Memory("vision", "motor");
  final List<FakeTransport> made = new ArrayList<>();

  /** Run Recorder as the runner does, with CAST_COMPONENT_ID c1 in vision and the server verifying {@code who}. */
  int run(Identity who, StringBuilder stderr) {
    Map<String, String> env = ArgsAndContractTest.env("{}"); // its CAST_TOKEN is no JWT: nothing decodes it
    PrintStream saved = System.err;
    ByteArrayOutputStream err = new ByteArrayOutputStream();
    System.setErr(new PrintStream(err, true, StandardCharsets.UTF_8));
    try {
      return Runner.run(new String[] {Recorder.class.getName()}, env, false, contract -> {
        FakeTransport t = new FakeTransport(memory, who);
        made.add(t);
        return t;
      });
    } finally {
      System.setErr(saved);
      stderr.append(err.toString(StandardCharsets.UTF_8));
    }
  }

  @Test
  void theComponentIsWhomTheServerVerified() {
    Recorder.SEEN.clear();
    StringBuilder err = new StringBuilder();
    assertEquals(0, run(new Identity("c1", "vision", true), err), err.toString());
    // Privileged because the server says so: the token of the environment is not even a JWT.
    assertEquals(List.of("c1@vision privileged"), Recorder.SEEN);
  }

  @Test
  void aLaunchEnvironmentForAnotherIdExitsWith2NamingBoth() {
    Recorder.SEEN.clear();
    StringBuilder err = new StringBuilder();
    assertEquals(2, run(new Identity("intruder", "vision", false), err));
    String message = err.toString();
    assertTrue(message.contains("CAST_COMPONENT_ID is 'c1' but the server verified the token as component 'intruder'"
        + " of subarchitecture 'vision'"), message);
    assertTrue(message.contains("`cast token c1 --sa vision`"), message);
    assertEquals(List.of(), Recorder.SEEN, "no hook runs");
    assertTrue(made.get(0).closed, "the session the server opened for the token's holder is ended");
  }

  @Test
  void aLaunchEnvironmentForAnotherSubarchitectureExitsWith2NamingBoth() {
    StringBuilder err = new StringBuilder();
    assertEquals(2, run(new Identity("c1", "motor", false), err));
    assertTrue(err.toString().contains("CAST_SUBARCHITECTURE is 'vision' but the server verified the token as"
        + " component 'c1' of subarchitecture 'motor'"), err.toString());
  }

  @Test
  void aComponentFailingTheCheckStaysUnconnected() {
    UnmanagedComponent c = new UnmanagedComponent() {};
    FakeTransport fake = new FakeTransport(memory, new Identity("x", "vision", false));
    InvalidArgumentError e = assertThrows(InvalidArgumentError.class, () -> c.bind(fake, who -> {
      throw new InvalidArgumentError("refused " + who.componentId());
    }));
    assertEquals("refused x", e.getMessage());
    assertTrue(fake.closed);
    assertThrows(IllegalStateException.class, c::componentId, "not connected");
  }

  @Test
  void connectOptionsThatContradictTheVerifiedIdentityAreRefused() {
    LaunchContract contract = new LaunchContract("e:1", "notebook", "vision", "token", Args.empty());
    ConnectResolver.Resolved found = new ConnectResolver.Resolved(contract, "CAST_ENDPOINT", "ConnectOptions.token");
    found.verify(new Identity("notebook", "vision", true));
    InvalidArgumentError id =
        assertThrows(InvalidArgumentError.class, () -> found.verify(new Identity("planner", "vision", true)));
    assertEquals(
        "ConnectOptions.componentId is 'notebook' but the server verified the token as component 'planner' of"
            + " subarchitecture 'vision': the token from ConnectOptions.token decides the identity; drop the option,"
            + " or give a token for it",
        id.getMessage());
    InvalidArgumentError sa =
        assertThrows(InvalidArgumentError.class, () -> found.verify(new Identity("notebook", "coordination", true)));
    assertTrue(sa.getMessage().startsWith("ConnectOptions.subarchitecture is 'vision' but the server verified the"
        + " token as component 'notebook' of subarchitecture 'coordination'"), sa.getMessage());
    // Options not given: any identity the token has.
    LaunchContract open = new LaunchContract("e:1", null, null, "token", Args.empty());
    new ConnectResolver.Resolved(open, "CAST_ENDPOINT", "CAST_TOKEN").verify(new Identity("planner", "x", false));
  }

  @Test
  void aConnectionIsWhomTheServerVerified() {
    FakeTransport fake = new FakeTransport(memory, new Identity("planner", "motor", true));
    try (Connection wm = new Connection(fake, who -> {})) {
      assertEquals("planner", wm.componentId());
      assertEquals("motor", wm.subarchitecture());
      assertTrue(wm.isPrivileged());
    }
  }
}
