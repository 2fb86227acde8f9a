package cast.testing;

import static org.junit.jupiter.api.Assertions.assertEquals;
import static org.junit.jupiter.api.Assertions.assertFalse;
import static org.junit.jupiter.api.Assertions.assertTrue;
import static org.junit.platform.engine.discovery.DiscoverySelectors.selectClass;

import cast.client.NotFoundError;
import com.google.protobuf.Int64Value;
import java.io.BufferedReader;
import java.io.ByteArrayOutputStream;
import java.io.InputStreamReader;
import java.io.PrintStream;
import java.nio.charset.StandardCharsets;
import java.nio.file.Files;
import java.nio.file.Path;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.concurrent.TimeUnit;
import org.junit.jupiter.api.Test;
import org.junit.jupiter.api.extension.RegisterExtension;
import org.junit.platform.testkit.engine.EngineTestKit;
import org.junit.platform.testkit.engine.Events;

/**
 * CastExtension runs a test class of its own through JUnit (EngineTestKit): the system is handed
 * to each test, a failed test's report has the server's output, and no server is left behind,
 * after a failed test nor after a test JVM killed with SIGKILL. And a missing server is named.
 */
class CastExtensionTest {
  static final List<String> SEEN = new ArrayList<>();

  /** The class the tests below run (not run by Surefire on its own: it is not named *Test). */
  static class Examined {
    @RegisterExtension static final CastExtension CAST = CastExtension.withSubarchitectures("arm");

    @Test
    void passes(LocalSystem system) {
      SEEN.add(system.directory().toString());
      assertEquals(List.of("arm"), system.subarchitectures());
    }

    @Test
    void fails(LocalSystem system) {
      SEEN.add(system.directory().toString());
      system.actAs("gripper", "arm").add("grip", Int64Value.of(1));
      system.assertEntry("arm", "grip", Int64Value.class, Int64Value.of(2));
    }
  }

  /** The processes whose command line names {@code text} (the server's names its system's directory). */
  static List<ProcessHandle> processesNaming(String text) {
    return ProcessHandle.allProcesses()
        .filter(p -> p.isAlive() && p.pid() != ProcessHandle.current().pid())
        .filter(p -> p.info().arguments().map(args -> String.join(" ", args).contains(text)).orElse(false))
        .toList();
  }

  @Test
  void handsASystemToEachTestAndLeavesNothingWhenOneFails() {
    SEEN.clear();
    PrintStream err = System.err;
    ByteArrayOutputStream printed = new ByteArrayOutputStream();
    Events tests;
    System.setErr(new PrintStream(printed, true, StandardCharsets.UTF_8));
    try {
      tests = EngineTestKit.engine("junit-jupiter").selectors(selectClass(Examined.class)).execute().testEvents();
    } finally {
      System.setErr(err);
    }
    assertEquals(1, tests.succeeded().count());
    assertEquals(1, tests.failed().count());
    Throwable cause = tests.failed().stream().findFirst().orElseThrow().getPayload(
        org.junit.platform.engine.TestExecutionResult.class).orElseThrow().getThrowable().orElseThrow();
    assertTrue(cause.getMessage().startsWith("entry 'grip' in subarchitecture 'arm' holds google.protobuf.Int64Value "
        + "{value: 1}"), cause.getMessage());
    String report = printed.toString(StandardCharsets.UTF_8);
    assertTrue(report.contains("cast system 'test' at 127.0.0.1:") && report.contains("listening on 127.0.0.1:"), report);
    assertEquals(2, SEEN.size());
    for (String directory : SEEN) {
      assertTrue(processesNaming(directory).isEmpty(), "a server of " + directory + " is still running");
      assertFalse(Files.exists(Path.of(directory)), directory + " is still there");
    }
  }

  /** The program the next test starts and kills: a system, its directory printed, then nothing. */
  public static final class KilledLater {
    public static void main(String[] args) throws Exception {
      LocalSystem system = LocalSystem.start("arm");
      System.out.println("directory " + system.directory());
      System.out.flush();
      Thread.sleep(120_000);
    }
  }

  @Test
  void aKilledTestJvmLeavesNoServerBehind() throws Exception {
    Process child = new ProcessBuilder(
            Path.of(System.getProperty("java.home"), "bin", "java").toString(), "-cp",
            System.getProperty("java.class.path"), KilledLater.class.getName())
        .redirectErrorStream(true).start();
    String directory = null;
    try (BufferedReader out = new BufferedReader(new InputStreamReader(child.getInputStream(), StandardCharsets.UTF_8))) {
      StringBuilder all = new StringBuilder();
      for (String line; (line = out.readLine()) != null; ) {
        all.append(line).append('\n');
        if (line.startsWith("directory ")) {
          directory = line.substring("directory ".length());
          break;
        }
      }
      assertTrue(directory != null, "the child printed no directory:\n" + all);
      assertEquals(1, processesNaming(directory).size(), "the child's server is not running");
      child.destroyForcibly(); // SIGKILL: no afterEach, no shutdown hook
      assertTrue(child.waitFor(30, TimeUnit.SECONDS));
      String killed = directory;
      CastTesting.waitFor(() -> processesNaming(killed).isEmpty(), Duration.ofSeconds(30),
          "the killed JVM's server to end");
    } finally {
      child.destroyForcibly();
      if (directory != null) {
        try (var files = Files.walk(Path.of(directory))) { // what a killed JVM cannot clean up itself
          for (Path p : files.sorted(java.util.Comparator.reverseOrder()).toList()) {
            Files.deleteIfExists(p);
          }
        }
      }
    }
  }

  @Test
  void namesWhatToInstallWhenThereIsNoServer() throws Exception {
    ProcessBuilder builder = new ProcessBuilder(
            Path.of(System.getProperty("java.home"), "bin", "java").toString(), "-cp",
            System.getProperty("java.class.path"), KilledLater.class.getName())
        .redirectErrorStream(true);
    builder.environment().put("CAST_SERVE", "/no/such/cast");
    Process child = builder.start();
    String printed = new String(child.getInputStream().readAllBytes(), StandardCharsets.UTF_8);
    assertTrue(child.waitFor(60, TimeUnit.SECONDS));
    assertEquals(1, child.exitValue(), printed);
    assertTrue(printed.contains(NotFoundError.class.getName() + ": CAST_SERVE names /no/such/cast, which is not an "
        + "executable file"), printed);
  }
}
