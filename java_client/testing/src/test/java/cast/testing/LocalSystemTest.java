package cast.testing;

import static cast.testing.CastTesting.waitFor;
import static org.junit.jupiter.api.Assertions.assertEquals;
import static org.junit.jupiter.api.Assertions.assertFalse;
import static org.junit.jupiter.api.Assertions.assertThrows;
import static org.junit.jupiter.api.Assertions.assertTrue;

import cast.client.Args;
import cast.client.Filters;
import cast.client.InvalidArgumentError;
import cast.client.Operation;
import cast.client.PermissionDeniedError;
import cast.client.Task;
import cast.client.TaskState;
import cast.client.UnavailableError;
import cast.client.UnmanagedComponent;
import cast.client.WorkingMemoryChange;
import cast.client.WriteResult;
import com.google.protobuf.Int64Value;
import com.google.protobuf.StringValue;
import java.nio.file.Files;
import java.nio.file.Path;
import java.time.Duration;
import java.util.List;
import org.junit.jupiter.api.Test;
import org.junit.jupiter.api.io.TempDir;

/**
 * The kit against the repository's own {@code cast serve} (CAST_SERVE, set by the build): a
 * component run and stepped, actors and their tasks, collected changes, the messages of failed
 * expectations, a configuration with variables, a restart.
 */
class LocalSystemTest {
  static Int64Value number(long n) {
    return Int64Value.of(n);
  }

  static StringValue text(String s) {
    return StringValue.of(s);
  }

  /** Counts to "to" in the entry "count" when an entry "go" appears; slow to start on purpose. */
  public static final class Counter extends UnmanagedComponent {
    long last;
    volatile boolean stopped;

    @Override
    public void configure(Args args) {
      last = args.getLong("to", 3);
    }

    @Override
    public void start() throws InterruptedException {
      Thread.sleep(300); // a watch registered late: run() must not hand it over before
      onChange(Filters.addressFilter("go", Operation.ADD), change -> {
        WriteResult result = add("count", number(0));
        for (long n = 1; n <= last; n++) {
          result = overwrite("count", number(n), result.version());
        }
      });
    }

    @Override
    public void stop() {
      stopped = true;
    }
  }

  /** Fails in start(). */
  public static final class Broken extends UnmanagedComponent {
    @Override
    public void start() {
      throw new IllegalStateException("no camera attached");
    }
  }

  @Test
  void runsAComponentAndHandsItOverOnceItsWatchesAreRegistered() {
    try (LocalSystem system = LocalSystem.start("vision", "language")) {
      assertEquals(List.of("vision", "language"), system.subarchitectures());
      RunningComponent<Counter> counter = system.run(new Counter(), "counter", "vision", Args.fromJson("{\"to\": 3}"));
      system.actAs("camera", "vision").add("go", text("now")); // right away: start() slept first
      assertEquals("counter", system.waitForEntry("vision", "count", Int64Value.class, number(3)).author());
      assertEquals(0, counter.stop());
      assertTrue(counter.component().stopped);
      assertFalse(counter.isRunning());
      assertEquals(1, system.run(new Broken(), "broken", "vision").join());
    }
  }

  @Test
  void stepsABoundComponentAndActsAsOthers() throws Exception {
    try (LocalSystem system = LocalSystem.start("vision", "language")) {
      Counter counter = system.bind(new Counter(), "counter", "vision");
      counter.configure(Args.fromJson("{\"to\": 2}"));
      counter.start();
      Actor camera = system.actAs("camera", "vision");
      camera.add("go", text("now"));
      system.waitForEntry("vision", "count", Int64Value.class, v -> v.getValue() == 2, Duration.ofSeconds(10));
      assertThrows(PermissionDeniedError.class, () -> camera.add("note", text("hi"), "language"));
      system.actAs("boss", "vision", true).add("order", text("go"), "language");
      assertEquals("boss", system.assertEntry("language", "order", StringValue.class).author());
      assertThrows(InvalidArgumentError.class, () -> system.actAs("camera", "motor"));
      var env = system.launchEnvironment("greeter", "language", Args.fromJson("{\"to\": 1}"), false);
      assertEquals(1, Args.fromJson(env.get("CAST_ARGS")).getInt("to", 0));
      assertEquals(List.of("CAST_ENDPOINT", "CAST_COMPONENT_ID", "CAST_SUBARCHITECTURE", "CAST_TOKEN", "CAST_ARGS"),
          List.copyOf(env.keySet()));
    }
  }

  @Test
  void servesAConfigurationAndItsTaskManagers(@TempDir Path dir) throws Exception {
    Path config = dir.resolve("tasks.yaml");
    Files.writeString(config, "system: tasks\nsubarchitectures:\n  ${SA:-vision}:\n"
        + "    task_manager: {policy: exclusive}\n");
    try (LocalSystem system = LocalSystem.start(new SystemOptions().config(config).set("SA", "planning"))) {
      assertEquals("tasks", system.name());
      assertEquals(List.of("planning"), system.subarchitectures());
      Actor planner = system.actAs("planner", "planning");
      Task first = planner.waitForDecision(planner.proposeTask("plan"));
      Task second = planner.waitForDecision(planner.proposeTask("plan again"));
      assertEquals(TaskState.ADOPTED, first.state());
      assertEquals(TaskState.REJECTED, second.state());
      assertEquals(2, planner.decisions().size());
    }
  }

  @Test
  void failedExpectationsSayWhatWasSeen() {
    try (LocalSystem system = LocalSystem.start("vision")) {
      ChangeCollector changes = system.collectChanges();
      system.actAs("counter", "vision").add("count", number(2));
      AssertionError wrong = assertThrows(AssertionError.class,
          () -> system.assertEntry("vision", "count", Int64Value.class, number(3)));
      assertTrue(wrong.getMessage().startsWith("entry 'count' in subarchitecture 'vision' holds "
          + "google.protobuf.Int64Value {value: 2} (version "), wrong.getMessage());
      assertTrue(wrong.getMessage().endsWith("by counter), expected google.protobuf.Int64Value {value: 3}"),
          wrong.getMessage());
      AssertionError missing = assertThrows(AssertionError.class,
          () -> system.assertEntry("vision", "counts", Int64Value.class));
      assertEquals("no entry 'counts' in subarchitecture 'vision'; entries there: count (google.protobuf.Int64Value)",
          missing.getMessage());
      AssertionError type = assertThrows(AssertionError.class,
          () -> system.assertEntry("vision", "count", StringValue.class));
      assertTrue(type.getMessage().contains("has type google.protobuf.Int64Value, not google.protobuf.StringValue"),
          type.getMessage());
      AssertionError late = assertThrows(AssertionError.class,
          () -> system.waitForEntry("vision", "count", Int64Value.class, number(3), Duration.ofMillis(200)));
      assertTrue(late.getMessage().startsWith("timed out after 0.2 s waiting for entry 'count' in subarchitecture "
          + "'vision': entry 'count' in subarchitecture 'vision' holds"), late.getMessage());
      changes.waitForCount(1);
      AssertionError fewer = assertThrows(AssertionError.class, () -> changes.waitForCount(2, Duration.ofMillis(200)));
      assertEquals("timed out after 0.2 s waiting for 2 changes; seen: 1 change:\n  ADD vision/count by counter "
          + "(revision 1): google.protobuf.Int64Value", fewer.getMessage());
      WorkingMemoryChange added = changes.waitForChange(c -> c.operation() == Operation.ADD);
      assertEquals(2, added.entry(Int64Value.class).value().getValue());
      AssertionError never = assertThrows(AssertionError.class,
          () -> waitFor(() -> false, Duration.ofMillis(50), "three greetings", () -> "one greeting"));
      assertEquals("timed out after 0.05 s waiting for three greetings; seen: one greeting", never.getMessage());
    }
  }

  @Test
  void restartsTheServerEmpty() {
    try (LocalSystem system = LocalSystem.start("vision")) {
      Actor camera = system.actAs("camera", "vision");
      camera.add("image", text("before"));
      system.restart();
      waitFor(() -> {
        try {
          camera.add("image", text("after"));
          return true;
        } catch (UnavailableError e) {
          return false;
        }
      }, Duration.ofSeconds(20), "the actor writing to the restarted server");
      system.assertEntry("vision", "image", StringValue.class, text("after"));
      assertTrue(system.output().contains("listening on "), system.output());
    }
  }
}
