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
