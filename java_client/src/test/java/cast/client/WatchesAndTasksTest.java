package cast.client;

import static cast.client.ComponentTest.counter;
import static cast.client.ComponentTest.eventually;
import static org.junit.jupiter.api.Assertions.*;

import cast.testing.CastTesting.Counter;
import cast.testing.CastTesting.Pose;
import java.time.Duration;
import java.util.ArrayList;
import java.util.Collections;
import java.util.HashSet;
import java.util.List;
import java.util.Set;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicReference;
import org.junit.jupiter.api.Test;

/**
 * Callbacks, watches, task hooks and the session as the component sees them, against
 * the in-memory fake transport. What the gRPC transport does below them (resuming a
 * broken Watch stream, registering a lost session again, heartbeats) is tested against
 * a real server by tests/interop/test_java_reliability.py and test_java_runner.py; the
 * resume's start revisions also by WatchStreamTest.
 */
class WatchesAndTasksTest extends WithFakeMemory {
  static final class Plain extends UnmanagedComponent {}

  static final class Hooks extends ManagedComponent {
    final List<String> seen = Collections.synchronizedList(new ArrayList<>());
    final AtomicReference<CastError> failed = new AtomicReference<>();
    final CountDownLatch watchFailedCalled = new CountDownLatch(1);

    @Override
    public void taskAdopted(Task task) {
      seen.add("adopted " + task.name() + " " + task.data(Counter.class));
      taskComplete(task, TaskOutcome.FAILED, "because");
    }

    @Override
    public void taskRejected(Task task) {
      seen.add("rejected " + task.name());
    }

    @Override
    public void watchFailed(CastError error) {
      failed.set(error);
      watchFailedCalled.countDown();
    }
  }

  @Test
  void callbacksRunOnOneDispatcherThreadInOrder() throws Exception {
    Plain writer = connect(new Plain(), "w", "vision");
    Plain watcher = connect(new Plain(), "watcher", "vision");
    List<Long> values = Collections.synchronizedList(new ArrayList<>());
    List<Counter> deleted = Collections.synchronizedList(new ArrayList<>());
    Set<Thread> threads = Collections.synchronizedSet(new HashSet<>());
    List<Boolean> onDispatcher = Collections.synchronizedList(new ArrayList<>());
    watcher.onChange(
        Filters.localTypeFilter(Counter.class).withEntry(),
        ch -> {
          if (ch.operation() == Operation.ADD) {
            values.add(ch.entry(Counter.class).value().getValue());
          } else {
            deleted.add(ch.entry(Counter.class).value()); // for a DELETE: the entry as it was
          }
          threads.add(Thread.currentThread());
          onDispatcher.add(watcher.onDispatcherThread());
        });
    List<String> ops = Collections.synchronizedList(new ArrayList<>());
    watcher.onChange(Filters.operationFilter(Operation.DELETE), ch -> ops.add(ch.operation() + " " + ch.id()));
    for (int i = 0; i < 50; i++) {
      writer.add("c" + i, counter("w", i));
    }
    writer.deleteEntry("c0");
    writer.add("other", Pose.getDefaultInstance());
    // Events travel on the watch stream, not with the write's answer: wait for them.
    assertTrue(
        eventually(() -> ops.size() == 1 && values.size() == 50 && deleted.size() == 1, Duration.ofSeconds(5)),
        values.toString());
    assertEquals(List.of(counter("w", 0)), deleted);
    assertTrue(watcher.drain(Duration.ofSeconds(5)));
    List<Long> expected = new ArrayList<>();
    for (long i = 0; i < 50; i++) {
      expected.add(i);
    }
    assertEquals(expected, values);
    assertEquals(1, threads.size());
    assertFalse(onDispatcher.contains(false));
    assertEquals(List.of("DELETE c0"), ops);
  }

  @Test
  void localFiltersAreSentWithTheOwnSubarchitecture() {
    Plain c = connect(new Plain(), "c1", "motor");
    c.onChange(
        List.of(
            Filters.localTypeFilter(Counter.class),
            Filters.addressFilter("x"),
            Filters.globalTypeFilter(Counter.class),
            Filters.operationFilter().inSubarchitecture("vision")),
        ch -> {});
    List<ChangeFilter> sent = FakeTransport.of(c).creates.get(0).filters();
    assertEquals(List.of("motor", "motor", "", "vision"), sent.stream().map(ChangeFilter::subarchitecture).toList());
    assertEquals(Filters.localTypeFilter(Counter.class).inSubarchitecture("motor"), sent.get(0));
    assertThrows(InvalidArgumentError.class, () -> c.onChange(List.of(), ch -> {}));
    assertThrows(InvalidArgumentError.class, () -> c.onChange(Filters.operationFilter(), null));
    assertEquals(1, FakeTransport.of(c).creates.size(), "refused before anything is sent");
  }

  @Test
  void cancelStopsDeliveryAndDropsQueuedCallbacks() throws Exception {
    Plain writer = connect(new Plain(), "w", "vision");
    Plain watcher = connect(new Plain(), "watcher", "vision");
    CountDownLatch blocked = new CountDownLatch(1);
    CountDownLatch release = new CountDownLatch(1);
    List<String> got = Collections.synchronizedList(new ArrayList<>());
    // A first callback holds the dispatcher so that the second watch's events queue up.
    watcher.onChange(
        Filters.addressFilter("gate"),
        ch -> {
          blocked.countDown();
          release.await(5, TimeUnit.SECONDS);
        });
    WatchHandle h = watcher.onChange(Filters.localTypeFilter(Counter.class), ch -> got.add(ch.id()));
    assertTrue(h.isActive());
    writer.add("gate", Pose.getDefaultInstance());
    assertTrue(blocked.await(5, TimeUnit.SECONDS));
    writer.add("queued", counter("w", 1));
    // The gate callback runs; the event for "queued" must be waiting behind it before the cancel.
    assertTrue(eventually(() -> watcher.pendingCallbacks() == 2, Duration.ofSeconds(5)));
    h.cancel();
    h.cancel(); // idempotent
    assertFalse(h.isActive());
    assertEquals(List.of(h.watchId()), FakeTransport.of(watcher).cancels, "the server is told once");
    release.countDown();
    writer.add("after", counter("w", 2));
    assertTrue(watcher.drain(Duration.ofSeconds(5)));
    assertEquals(List.of(), got, "a cancelled watch delivers nothing, not even what was queued");
  }

  @Test
  void aWatchStreamThatEndedForGoodCallsWatchFailed() throws Exception {
    Hooks watcher = connect(new Hooks(), "watcher", "vision");
    WatchHandle h = watcher.onChange(Filters.operationFilter(), ch -> {});
    // As the gRPC transport reports a stream ended with OUT_OF_RANGE: every watch on it.
    FakeTransport.of(watcher).failWatch(-1, new HistoryExpiredError("revision 3 is older than the history"));
    assertTrue(watcher.watchFailedCalled.await(5, TimeUnit.SECONDS));
    assertEquals(HistoryExpiredError.class, watcher.failed.get().getClass());
    assertEquals("revision 3 is older than the history", watcher.failed.get().getMessage());
    assertSame(watcher.failed.get(), h.error());
    // Resynchronising: a new onChange works again.
    Plain writer = connect(new Plain(), "w", "vision");
    List<String> got = Collections.synchronizedList(new ArrayList<>());
    watcher.onChange(Filters.localTypeFilter(Counter.class), ch -> got.add(ch.id()));
    writer.add("again", counter("w", 1));
    assertTrue(eventually(() -> got.size() == 1, Duration.ofSeconds(5)));
    assertEquals(List.of("again"), got);
  }

  @Test
  void aResumeTheServerRefusesIsTheResynchroniseSignal() throws Exception {
    Hooks watcher = connect(new Hooks(), "watcher", "vision");
    WatchHandle h = watcher.onChange(Filters.operationFilter(), ch -> {});
    WatchHandle other = watcher.onChange(Filters.localTypeFilter(Counter.class), ch -> {});
    // As the gRPC transport reports a resume the server refused (its history is gone): that watch only.
    FakeTransport.of(watcher).failWatch(h.watchId(), new HistoryExpiredError("history-1 is gone: resynchronise"));
    assertTrue(watcher.watchFailedCalled.await(10, TimeUnit.SECONDS));
    assertEquals(HistoryExpiredError.class, watcher.failed.get().getClass());
    assertTrue(watcher.failed.get().getMessage().contains("resynchronise"), watcher.failed.get().getMessage());
    assertFalse(h.isActive(), "the watch that could not resume is dropped");
    assertSame(watcher.failed.get(), h.error());
    assertTrue(other.isActive());
    assertNull(other.error());
  }

  @Test
  void managedComponentHooksRunOnTheDispatcher() throws Exception {
    Hooks m = connect(new Hooks(), "m", "vision");
    Task t = m.proposeTask("work", counter("m", 7), 3);
    assertEquals(TaskState.WAITING, t.state());
    assertEquals(7, t.data(Counter.class).getValue());
    assertEquals(3, t.priority());
    assertEquals("m", t.component());
    m.proposeTask("reject-me");
    assertTrue(eventually(() -> m.seen.size() == 2, Duration.ofSeconds(5)), m.seen.toString());
    assertTrue(m.drain(Duration.ofSeconds(5)));
    assertTrue(m.seen.get(0).startsWith("adopted work "), m.seen.toString());
    assertEquals("rejected reject-me", m.seen.get(1));
    assertTrue(memory.calls.contains("Complete t1 FAILED because"), memory.calls.toString());
    m.retractTask(t);
    assertTrue(memory.calls.contains("Retract t1"));
    assertThrows(InvalidArgumentError.class, () -> m.proposeTask(""));
  }

  @Test
  void aSessionIsStartedWithTheComponentsKindAndEndedOnClose() {
    Plain plain = connect(new Plain(), "c1", "vision");
    Hooks managed = connect(new Hooks(), "m1", "vision");
    assertEquals(List.of("java unmanaged"), FakeTransport.of(plain).sessions);
    assertEquals(List.of("java managed"), FakeTransport.of(managed).sessions);
    FakeTransport fake = FakeTransport.of(plain);
    assertEquals(ComponentState.STARTING, fake.state.get());
    plain.close();
    components.remove(plain);
    assertTrue(fake.closed, "closing the component ends its session");
  }

  @Test
  void aStateChangeIsReportedAtOnce() {
    Plain c = connect(new Plain(), "c1", "vision");
    FakeTransport fake = FakeTransport.of(c);
    assertEquals(List.of(), fake.reported);
    c.setState(ComponentState.RUNNING);
    assertEquals(List.of(ComponentState.RUNNING), fake.reported, "reported when it happens, not at the next beat");
    c.setState(ComponentState.STOPPING);
    assertEquals(ComponentState.STOPPING, fake.state.get());
    assertEquals(2, fake.reported.size());
  }
}
