package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import com.google.protobuf.Int64Value;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.concurrent.CopyOnWriteArrayList;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.TimeUnit;
import org.junit.jupiter.api.AfterAll;
import org.junit.jupiter.api.BeforeAll;
import org.junit.jupiter.api.Test;
import org.junit.jupiter.api.TestInstance;

/**
 * Delivery policies and receiver priorities against a real server ({@link RealServer}): a
 * LATEST watch whose callback is slow sees few calls, the newest value within one callback of
 * the writer stopping, and every skipped revision counted; a QUEUE watch sees every change;
 * a pending HIGH callback runs before pending LOW ones.
 */
@TestInstance(TestInstance.Lifecycle.PER_CLASS)
class DeliveryTest {
  private static final int WRITES = 50;
  private RealServer server;

  @BeforeAll
  void startServer() throws Exception {
    server = new RealServer();
  }

  @AfterAll
  void stopServer() throws Exception {
    server.close();
  }

  /** One callback: the value it got, that change's revision and skip counts, and when it began. */
  private record Call(long value, long revision, long skipped, long firstSkipped, long began) {}

  /** Overwrite {@code id} (added first, before the watch) WRITES times while {@code options}' watch sleeps {@code sleepMs} per call. */
  private List<Call> watchAWriter(String id, WatchOptions options, long sleepMs, long[] writerStopped)
      throws Exception {
    List<Call> calls = new CopyOnWriteArrayList<>();
    try (Connection writer = server.connect("writer-" + id, "vision", false, null);
        Connection reader = server.connect("reader-" + id, "vision", false, null)) {
      WriteResult added = writer.add(id, Int64Value.of(0));
      reader.onChange(
          Filters.addressFilter(new WorkingMemoryAddress(id, "vision")).withEntry(),
          change -> {
            calls.add(new Call(change.entry(Int64Value.class).value().getValue(), change.revision(), change.skipped(),
                change.firstSkippedRevision(), System.nanoTime()));
            Thread.sleep(sleepMs);
          },
          options);
      WriteResult last = null;
      for (int i = 1; i <= WRITES; i++) {
        last = writer.overwrite(id, Int64Value.of(i));
      }
      writerStopped[0] = System.nanoTime();
      assertEquals(added.revision() + WRITES, last.revision(), "no other write in between");
      RealServer.waitFor(
          () -> !calls.isEmpty() && calls.get(calls.size() - 1).value() == WRITES, Duration.ofSeconds(60),
          "the newest value");
      assertTrue(reader.drain(Duration.ofSeconds(30)));
      // Nothing lost silently: each call's skipped revisions lie between the previous call's and its own.
      long previous = added.revision();
      for (Call c : calls) {
        assertEquals(previous + c.skipped() + 1, c.revision(), calls.toString());
        assertEquals(c.skipped() == 0 ? 0 : previous + 1, c.firstSkipped(), calls.toString());
        previous = c.revision();
      }
      assertEquals(last.revision(), previous);
    }
    return calls;
  }

  @Test
  void aLatestWatchWithASlowCallbackSeesTheNewestValueSoonAndCountsWhatItSkipped() throws Exception {
    long[] stopped = new long[1];
    List<Call> calls = watchAWriter("frame", WatchOptions.latest(), 200, stopped);
    assertTrue(calls.size() < WRITES / 2, "far fewer calls than changes: " + calls);
    assertEquals(WRITES, calls.stream().mapToLong(c -> c.skipped() + 1).sum(), calls.toString());
    // The call running when the writer stopped, then the newest value (one more may have begun
    // just before the last change arrived).
    long begunAfter = calls.stream().filter(c -> c.began() > stopped[0]).count();
    assertTrue(begunAfter <= 2, begunAfter + " calls began after the writer stopped: " + calls);
  }

  @Test
  void aQueueWatchSeesEveryChangeInOrder() throws Exception {
    List<Call> calls = watchAWriter("queued", WatchOptions.queue(), 10, new long[1]);
    List<Long> values = new ArrayList<>();
    for (Call c : calls) {
      values.add(c.value());
      assertEquals(0, c.skipped());
    }
    assertEquals(java.util.stream.LongStream.rangeClosed(1, WRITES).boxed().toList(), values);
  }

  @Test
  void aPendingHighPriorityCallbackRunsBeforePendingLowOnes() throws Exception {
    try (Connection wm = server.connect("prioritiser", "vision", false, null)) {
      CountDownLatch busy = new CountDownLatch(1);
      CountDownLatch release = new CountDownLatch(1);
      List<String> order = new CopyOnWriteArrayList<>();
      wm.onChange(Filters.addressFilter(new WorkingMemoryAddress("gate", "vision")), c -> {
        busy.countDown();
        release.await(30, TimeUnit.SECONDS);
      });
      wm.onChange(
          Filters.addressFilter(new WorkingMemoryAddress("low", "vision")).withEntry(),
          c -> order.add("low " + c.entry(Int64Value.class).value().getValue()),
          WatchOptions.defaults().priority(Priority.LOW));
      wm.onChange(
          Filters.addressFilter(new WorkingMemoryAddress("high", "vision")),
          c -> order.add("high"),
          WatchOptions.defaults().priority(Priority.HIGH));
      wm.add("gate", Int64Value.of(0));
      assertTrue(busy.await(30, TimeUnit.SECONDS), "the dispatcher is busy");
      wm.add("low", Int64Value.of(1));
      wm.overwrite("low", Int64Value.of(2));
      wm.overwrite("low", Int64Value.of(3));
      wm.add("high", Int64Value.of(0));
      RealServer.waitFor(() -> wm.pendingCallbacks() == 5, Duration.ofSeconds(30), "the gate and four pending callbacks");
      release.countDown();
      assertTrue(wm.drain(Duration.ofSeconds(30)));
      assertEquals(List.of("high", "low 1", "low 2", "low 3"), order);
    }
  }
}
