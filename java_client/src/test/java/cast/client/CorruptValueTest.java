package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.testing.CastTesting.Counter;
import cast.testing.CastTesting.Pose;
import com.google.protobuf.Any;
import com.google.protobuf.ByteString;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.TimeUnit;
import org.junit.jupiter.api.Test;

/**
 * A stored value whose bytes do not parse as its declared type (written corrupt, or
 * with another schema) is an InvalidArgumentError naming the entry's id, SA and type,
 * wherever the library decodes one: get, getEntry, getAll, the entry of a change
 * event, the data of a task.
 */
class CorruptValueTest {
  /** Field 1 (writer, a string) said to be 5 bytes long, with 2 left: no Counter. */
  static final Any CORRUPT =
      Any.newBuilder()
          .setTypeUrl(Types.TYPE_URL_PREFIX + "cast.testing.Counter")
          .setValue(ByteString.copyFrom(new byte[] {0x0a, 0x05, 'a', 'b'}))
          .build();

  static final String PREFIX = "entry 'bad' in subarchitecture 'vision' does not parse as cast.testing.Counter (";
  static final String SUFFIX = "): it was written corrupt or with another schema; overwrite or delete it";

  final FakeTransport.Memory memory = new FakeTransport.Memory("vision");

  static void assertNamesTheEntry(String message) {
    assertTrue(message.startsWith(PREFIX) && message.endsWith(SUFFIX), message);
  }

  @Test
  void getGetEntryAndGetAllSayWhichEntry() {
    try (UnmanagedComponent c = FakeTransport.connect(new UnmanagedComponent() {}, memory, "reader", "vision")) {
      // Straight through the transport: the component API always writes valid values.
      c.transport().add("vision", "bad", CORRUPT);
      assertNamesTheEntry(assertThrows(InvalidArgumentError.class, () -> c.get("bad", Counter.class)).getMessage());
      assertNamesTheEntry(
          assertThrows(InvalidArgumentError.class, () -> c.getEntry("bad", Counter.class)).getMessage());
      assertNamesTheEntry(assertThrows(InvalidArgumentError.class, () -> c.getAll(Counter.class)).getMessage());
    }
  }

  @Test
  void theEntryOfAChangeEventSaysWhichEntry() throws Exception {
    try (UnmanagedComponent c = FakeTransport.connect(new UnmanagedComponent() {}, memory, "reader", "vision")) {
      CompletableFuture<String> seen = new CompletableFuture<>();
      c.onChange(
          Filters.localTypeFilter(Counter.class).withEntry(),
          change -> {
            try {
              change.entry(Counter.class);
              seen.complete("(no error)");
            } catch (InvalidArgumentError e) {
              seen.complete(e.getMessage());
            }
          });
      c.transport().add("vision", "bad", CORRUPT);
      assertNamesTheEntry(seen.get(10, TimeUnit.SECONDS));
    }
  }

  /** Hands the error of reading each adopted task's data to the test. */
  static final class Tasks extends ManagedComponent {
    final CompletableFuture<String> seen = new CompletableFuture<>();

    @Override
    public void taskAdopted(Task task) {
      try {
        task.data(Counter.class);
        seen.complete("(no error)");
      } catch (InvalidArgumentError e) {
        seen.complete(e.getMessage());
      }
    }
  }

  @Test
  void theDataOfATaskSaysWhichTask() throws Exception {
    try (Tasks c = FakeTransport.connect(new Tasks(), memory, "worker", "vision")) {
      c.transport().propose("work", CORRUPT, 0);
      String message = c.seen.get(10, TimeUnit.SECONDS);
      assertTrue(message.startsWith("task 't1' data in subarchitecture '"), message);
      assertTrue(message.contains("' does not parse as cast.testing.Counter ("), message);
      assertTrue(
          message.endsWith("): it was proposed corrupt or with another schema; complete or retract the task"), message);
    }
  }

  @Test
  void aWrongTypeIsStillNamedAsSuchWithItsSubarchitecture() {
    try (UnmanagedComponent c = FakeTransport.connect(new UnmanagedComponent() {}, memory, "reader", "vision")) {
      c.add("pose", Pose.getDefaultInstance());
      assertEquals(
          "entry 'pose' in subarchitecture 'vision' has type cast.testing.Pose, not cast.testing.Counter: read it"
              + " with the right class",
          assertThrows(InvalidArgumentError.class, () -> c.get("pose", Counter.class)).getMessage());
    }
  }

  @Test
  void theDataOfATaskOfAnotherTypeSaysWhichTaskAndWhere() throws Exception {
    try (Tasks c = FakeTransport.connect(new Tasks(), memory, "worker", "vision")) {
      c.transport().propose("work", Types.pack(Pose.getDefaultInstance()), 0);
      assertEquals(
          "task 't1' data in subarchitecture 'vision' has type cast.testing.Pose, not cast.testing.Counter: read it"
              + " with the right class",
          c.seen.get(10, TimeUnit.SECONDS));
    }
  }
}
