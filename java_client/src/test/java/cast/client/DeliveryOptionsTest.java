package cast.client;

import static cast.client.ComponentTest.counter;
import static cast.client.ComponentTest.eventually;
import static org.junit.jupiter.api.Assertions.*;

import cast.testing.CastTesting.Counter;
import java.time.Duration;
import java.util.List;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.CopyOnWriteArrayList;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.ExecutionException;
import java.util.concurrent.TimeUnit;
import org.junit.jupiter.api.Test;

/**
 * {@link WatchOptions} and the asynchronous writes as the component sees them, against the
 * in-memory fake: the options reach the transport, a LATEST watch keeps one undelivered change
 * per entry in the component's queue and counts what it replaced, exactly; addAsync and
 * overwriteAsync hand their refusals to the future. Against a real server: DeliveryTest,
 * WriteStreamTest.
 */
class DeliveryOptionsTest extends WithFakeMemory {
  static final class Plain extends UnmanagedComponent {}

  @Test
  void optionsAreImmutableValuesWithTheDefaultsOfOnChange() {
    WatchOptions high = WatchOptions.latest().priority(Priority.HIGH);
    assertEquals(Delivery.LATEST, high.delivery());
    assertEquals(Priority.HIGH, high.priority());
    assertEquals(Delivery.LATEST, WatchOptions.latest().delivery(), "latest() itself did not change");
    assertEquals(WatchOptions.queue(), WatchOptions.defaults());
    assertEquals(Priority.MEDIUM, WatchOptions.defaults().priority());
    assertEquals(WatchOptions.defaults().delivery(Delivery.LATEST), WatchOptions.latest());
    assertThrows(InvalidArgumentError.class, () -> WatchOptions.defaults().priority(null));
    Plain c = connect(new Plain(), "c", "vision");
    assertThrows(InvalidArgumentError.class, () -> c.onChange(Filters.addressFilter("x"), ch -> {}, null));
  }

  @Test
  void theDeliveryGoesToTheWatchCreate() {
    Plain c = connect(new Plain(), "c", "vision");
    c.onChange(Filters.addressFilter("x"), ch -> {});
    c.onChange(Filters.addressFilter("y"), ch -> {}, WatchOptions.latest().priority(Priority.LOW));
    List<FakeTransport.Created> creates = FakeTransport.of(c).creates;
    assertEquals(Delivery.QUEUE, creates.get(0).delivery());
    assertEquals(Delivery.LATEST, creates.get(1).delivery());
  }

  @Test
  void aLatestWatchKeepsOneUndeliveredChangePerEntryInRevisionOrder() throws Exception {
    Plain writer = connect(new Plain(), "w", "vision");
    Plain reader = connect(new Plain(), "r", "vision");
    CountDownLatch busy = new CountDownLatch(1);
    CountDownLatch release = new CountDownLatch(1);
    reader.onChange(Filters.addressFilter("gate"), ch -> {
      busy.countDown();
      release.await(30, TimeUnit.SECONDS);
    });
    List<WorkingMemoryChange> seen = new CopyOnWriteArrayList<>();
    reader.onChange(
        List.of(Filters.addressFilter("a").withEntry(), Filters.addressFilter("b").withEntry()), seen::add,
        WatchOptions.latest());
    writer.add("gate", counter("w", 0)); // revision 1
    assertTrue(busy.await(10, TimeUnit.SECONDS));
    writer.add("a", counter("w", 1)); // 2
    writer.add("b", counter("w", 1)); // 3
    writer.overwrite("a", counter("w", 2)); // 4: replaces a@2, behind b@3
    writer.overwrite("b", counter("w", 2)); // 5: replaces b@3
    writer.overwrite("a", counter("w", 3)); // 6: replaces a@4 (which had replaced a@2)
    assertTrue(eventually(() -> FakeTransport.of(writer).memory.revisions.get("vision") == 6, Duration.ofSeconds(5)));
    Thread.sleep(200); // the fake's reader delivers events on its own thread: let it finish
    assertEquals(3, reader.pendingCallbacks(), "the gate and one change per entry");
    release.countDown();
    assertTrue(reader.drain(Duration.ofSeconds(10)));
    assertEquals(2, seen.size(), seen.toString());
    WorkingMemoryChange b = seen.get(0);
    WorkingMemoryChange a = seen.get(1);
    assertEquals(List.of("b", 5L, 1L, 3L), List.of(b.id(), b.revision(), b.skipped(), b.firstSkippedRevision()));
    assertEquals(List.of("a", 6L, 2L, 2L), List.of(a.id(), a.revision(), a.skipped(), a.firstSkippedRevision()));
    assertEquals(3, a.entry(Counter.class).value().getValue(), "the newest value");
  }

  @Test
  void asyncWritesHandTheirRefusalsToTheFuture() throws Exception {
    Plain c = connect(new Plain(), "c", "vision");
    WriteResult first = c.addAsync("x", counter("c", 1)).get(5, TimeUnit.SECONDS);
    CompletableFuture<WriteResult> again = c.addAsync("x", counter("c", 2));
    ExecutionException e = assertThrows(ExecutionException.class, () -> again.get(5, TimeUnit.SECONDS));
    assertInstanceOf(AlreadyExistsError.class, e.getCause());
    CompletableFuture<WriteResult> stale = c.overwriteAsync("x", counter("c", 3), first.version() + 1);
    e = assertThrows(ExecutionException.class, () -> stale.get(5, TimeUnit.SECONDS));
    assertInstanceOf(ConsistencyError.class, e.getCause());
    assertEquals(first.version() + 1, c.overwriteAsync("x", counter("c", 4), "vision", first.version()).get().version());
    assertEquals(4, c.get("x", Counter.class).getValue());
  }
}
