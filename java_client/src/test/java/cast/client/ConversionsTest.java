package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.testing.CastTesting.Counter;
import com.google.protobuf.Timestamp;
import java.time.Instant;
import java.util.List;
import org.junit.jupiter.api.Test;

/** Wire messages to library types and back: every value of every enum, and what a message may leave out. */
class ConversionsTest {
  @Test
  void enumsMapOneToOne() {
    for (Operation op : Operation.values()) {
      assertEquals(op, Conversions.operation(Conversions.operation(op)));
      assertTrue(Conversions.operation(op).name().endsWith(op.name()));
    }
    for (LockMode m : LockMode.values()) {
      assertEquals("LOCK_MODE_" + m.name(), Conversions.lockMode(m).name());
    }
    for (TaskOutcome o : TaskOutcome.values()) {
      assertEquals("TASK_OUTCOME_" + o.name(), Conversions.outcome(o).name());
    }
    for (Delivery d : Delivery.values()) {
      assertEquals("DELIVERY_" + d.name(), Conversions.delivery(d).name());
    }
    assertEquals(cast.v1.Delivery.DELIVERY_QUEUE, Conversions.delivery(Delivery.QUEUE), "the wire's default");
    for (ComponentState s : ComponentState.values()) {
      assertEquals("COMPONENT_STATE_" + s.name(), Conversions.state(s).name());
    }
    for (cast.v1.TaskState s : cast.v1.TaskState.values()) {
      if (s != cast.v1.TaskState.UNRECOGNIZED) {
        assertEquals(s.name().replace("TASK_STATE_", ""), Conversions.taskState(s).name());
      }
    }
  }

  @Test
  void anEventOfAnUnknownOperationIsRefusedByName() {
    var event = cast.v1.ChangeEvent.newBuilder().setRevision(4).build(); // OPERATION_UNSPECIFIED
    InvalidArgumentError e = assertThrows(InvalidArgumentError.class, () -> Conversions.change(event));
    assertEquals("unknown operation OPERATION_UNSPECIFIED in a change event", e.getMessage());
  }

  @Test
  void anEventCarriesItsEntryOnlyWhenTheServerSentIt() {
    var address = cast.v1.EntryAddress.newBuilder().setId("x").setSubarchitecture("vision");
    Counter value = Counter.newBuilder().setValue(3).build();
    var entry = cast.v1.Entry.newBuilder().setAddress(address).setType("cast.testing.Counter")
        .setValue(Types.pack(value)).setVersion(2).setAuthor("w").setRevision(5)
        .setModified(Timestamp.newBuilder().setSeconds(10).setNanos(20));
    var event = cast.v1.ChangeEvent.newBuilder().setRevision(5).setOperation(cast.v1.Operation.OPERATION_OVERWRITE)
        .setAddress(address).setType("cast.testing.Counter").setVersion(2).setSourceComponent("w")
        .setSourceSubarchitecture("motor").setTime(Timestamp.newBuilder().setSeconds(11)).addWatchIds(1).addWatchIds(3);
    Transport.Change bare = Conversions.change(event.build());
    assertNull(bare.entry());
    assertEquals(List.of(1, 3), bare.watchIds());
    assertEquals(new WorkingMemoryAddress("x", "vision"), bare.address());
    assertEquals(Instant.ofEpochSecond(11), bare.time());
    WorkingMemoryChange change = new WorkingMemoryChange(Conversions.change(event.setEntry(entry).build()));
    assertTrue(change.hasEntry());
    assertEquals("motor", change.sourceSubarchitecture());
    Entry<Counter> got = change.entry(Counter.class);
    assertEquals(value, got.value());
    assertEquals(Instant.ofEpochSecond(10, 20), got.modified());
    assertEquals(List.of(2L, 5L, "w"), List.of(got.version(), got.revision(), got.author()));
  }

  @Test
  void anEventSaysWhatALatestWatchSkippedAndANewerChangeInTheQueueAddsToIt() {
    var address = cast.v1.EntryAddress.newBuilder().setId("x").setSubarchitecture("vision");
    var event = cast.v1.ChangeEvent.newBuilder().setRevision(9).setOperation(cast.v1.Operation.OPERATION_OVERWRITE)
        .setAddress(address).addWatchIds(1);
    Transport.Change none = Conversions.change(event.build());
    assertEquals(List.of(0L, 0L), List.of(none.skipped(), none.firstSkippedRevision()));
    Transport.Change older = Conversions.change(event.setSkipped(3).setFirstSkippedRevision(5).build());
    assertEquals(List.of(3L, 5L), List.of(older.skipped(), older.firstSkippedRevision()));
    // The server skipped 5..8 for the older (9); a newer one (12, itself skipping 10..11) replaces it in the queue.
    Transport.Change newer = Conversions.change(event.setRevision(12).setSkipped(2).setFirstSkippedRevision(10).build());
    Transport.Change merged = newer.superseding(older);
    assertEquals(List.of(12L, 6L, 5L), List.of(merged.revision(), merged.skipped(), merged.firstSkippedRevision()));
    // Neither skipped anything: the newer skipped the older alone.
    Transport.Change next = Conversions.change(event.setRevision(10).setSkipped(0).setFirstSkippedRevision(0).build());
    Transport.Change replaced = next.superseding(none);
    assertEquals(List.of(10L, 1L, 9L), List.of(replaced.revision(), replaced.skipped(), replaced.firstSkippedRevision()));
  }

  @Test
  void aLockOnTheStreamCarriesItsTimeoutForTheServerToEndTheWait() {
    assertEquals(0, Conversions.writeLock("vision", "x", LockMode.O, false, null).getTimeoutMs(), "forever");
    assertEquals(0, Conversions.writeLock("vision", "x", LockMode.O, true, java.time.Duration.ofSeconds(3)).getTimeoutMs());
    assertEquals(1500, Conversions.writeLock("vision", "x", LockMode.O, false, java.time.Duration.ofMillis(1500)).getTimeoutMs());
    assertEquals(1, Conversions.writeLock("vision", "x", LockMode.O, false, java.time.Duration.ZERO).getTimeoutMs());
    int longest = Conversions.writeLock("vision", "x", LockMode.ODR, false, java.time.Duration.ofDays(100)).getTimeoutMs();
    assertEquals(Conversions.MAX_LOCK_TIMEOUT_MS, Integer.toUnsignedLong(longest), "as much as the uint32 carries");
    var lock = Conversions.writeLock("motor", "y", LockMode.ODR, true, null).getLock();
    assertEquals(List.of("motor", "y", true), List.of(lock.getAddress().getSubarchitecture(), lock.getAddress().getId(), lock.getNoWait()));
  }

  @Test
  void aTaskWithoutDataHasNone() {
    Task t = Conversions.task(cast.v1.Task.newBuilder().setTaskId("t1").setName("n")
        .setState(cast.v1.TaskState.TASK_STATE_ADOPTED).build());
    assertFalse(t.hasData());
    assertNull(t.data(Counter.class));
    assertEquals(TaskState.ADOPTED, t.state());
  }

  @Test
  void batchWritesKeepTheirOrderAndVersions() {
    var writes = List.of(
        new Transport.Write(Operation.ADD, "a", Types.pack(Counter.getDefaultInstance()), null),
        new Transport.Write(Operation.OVERWRITE, "b", Types.pack(Counter.getDefaultInstance()), 3L),
        new Transport.Write(Operation.DELETE, "c", null, null));
    cast.v1.BatchRequest req = Conversions.batch("vision", writes);
    assertEquals("a", req.getOperations(0).getAdd().getAddress().getId());
    assertEquals(3L, req.getOperations(1).getOverwrite().getExpectedVersion());
    assertFalse(req.getOperations(2).getDelete().hasExpectedVersion());
    assertEquals("vision", req.getOperations(2).getDelete().getAddress().getSubarchitecture());
  }

  @Test
  void aLocalFilterMustHaveItsSubarchitectureFirst() {
    assertThrows(IllegalArgumentException.class, () -> Conversions.filter(Filters.addressFilter("x")));
  }
}
