package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.testing.CastTesting.Counter;
import cast.testing.CastTesting.Pose;
import java.util.List;
import java.util.Set;
import org.junit.jupiter.api.Test;

/** The filter helpers, and the filters as they go on the wire (the own SA filled in, then Conversions). */
class FiltersTest {
  /** What a component sends for {@code f}: a local filter gets the own SA {@code own}, then the wire form. */
  static cast.v1.ChangeFilter wire(ChangeFilter f, String own) {
    return Conversions.filter(f.isLocal() ? f.inSubarchitecture(own) : f);
  }

  @Test
  void localTypeFilterWatchesTheOwnSubarchitecture() {
    ChangeFilter f = Filters.localTypeFilter(Counter.class, Operation.ADD);
    assertTrue(f.isLocal());
    cast.v1.ChangeFilter pb = wire(f, "vision");
    assertEquals("cast.testing.Counter", pb.getType());
    assertEquals("vision", pb.getSubarchitecture());
    assertEquals(List.of(cast.v1.Operation.OPERATION_ADD), pb.getOperationsList());
    assertFalse(pb.getIncludeEntry());
  }

  @Test
  void globalTypeFilterWatchesEverySubarchitecture() {
    cast.v1.ChangeFilter pb = wire(Filters.globalTypeFilter(Pose.class), "vision");
    assertEquals("cast.testing.Pose", pb.getType());
    assertEquals("", pb.getSubarchitecture(), "empty SA means every SA on the wire");
    assertTrue(pb.getOperationsList().isEmpty(), "no operations means every operation");
  }

  @Test
  void typeFiltersAcceptTypeNames() {
    assertEquals(
        Filters.localTypeFilter(Counter.class), Filters.localTypeFilter("cast.testing.Counter"));
    assertEquals(
        Filters.globalTypeFilter(Counter.class), Filters.globalTypeFilter("cast.testing.Counter"));
  }

  @Test
  void addressFilterDefaultsToTheOwnSubarchitecture() {
    cast.v1.ChangeFilter own = wire(Filters.addressFilter("e1", Operation.OVERWRITE, Operation.DELETE), "motor");
    assertEquals("e1", own.getId());
    assertEquals("motor", own.getSubarchitecture());
    assertEquals(
        Set.of(cast.v1.Operation.OPERATION_OVERWRITE, cast.v1.Operation.OPERATION_DELETE),
        Set.copyOf(own.getOperationsList()));
    cast.v1.ChangeFilter other =
        wire(Filters.addressFilter(new WorkingMemoryAddress("e2", "language")), "motor");
    assertEquals("e2", other.getId());
    assertEquals("language", other.getSubarchitecture());
  }

  @Test
  void sourceFilterMatchesAComponentEverywhere() {
    cast.v1.ChangeFilter pb = wire(Filters.sourceFilter("planner"), "vision");
    assertEquals("planner", pb.getSourceComponent());
    assertEquals("", pb.getSubarchitecture());
    assertEquals("", pb.getType());
  }

  @Test
  void operationFilterIsGlobalUnlessMadeLocal() {
    ChangeFilter deletes = Filters.operationFilter(Operation.DELETE);
    assertEquals("", wire(deletes, "vision").getSubarchitecture());
    assertEquals("vision", wire(deletes.local(), "vision").getSubarchitecture());
    assertEquals("motor", wire(deletes.inSubarchitecture("motor"), "vision").getSubarchitecture());
    assertEquals(List.of(cast.v1.Operation.OPERATION_DELETE), wire(deletes, "x").getOperationsList());
  }

  @Test
  void withersReturnNewFiltersAndLeaveTheOriginal() {
    ChangeFilter f = Filters.globalTypeFilter(Counter.class);
    ChangeFilter g = f.withEntry().withOperations(Operation.ADD).fromSubarchitecture("language");
    assertFalse(f.includeEntry());
    assertTrue(f.operations().isEmpty());
    assertTrue(g.includeEntry());
    assertEquals(Set.of(Operation.ADD), g.operations());
    cast.v1.ChangeFilter pb = wire(g, "vision");
    assertTrue(pb.getIncludeEntry());
    assertEquals("language", pb.getSourceSubarchitecture());
    assertNotEquals(f, g);
    assertThrows(UnsupportedOperationException.class, () -> g.operations().add(Operation.DELETE));
  }

  @Test
  void badArgumentsAreRefusedWithAClearMessage() {
    InvalidArgumentError e = assertThrows(InvalidArgumentError.class, () -> Filters.addressFilter(""));
    assertTrue(e.getMessage().contains("entry id"), e.getMessage());
    assertThrows(InvalidArgumentError.class, () -> Filters.sourceFilter(null));
    assertThrows(InvalidArgumentError.class, () -> Filters.localTypeFilter(""));
    assertThrows(InvalidArgumentError.class, () -> Filters.operationFilter(Operation.ADD, null));
    InvalidArgumentError notMessage =
        assertThrows(InvalidArgumentError.class, () -> Filters.localTypeFilter(com.google.protobuf.Message.class));
    assertTrue(notMessage.getMessage().contains("not a generated protobuf message class"), notMessage.getMessage());
  }
}
