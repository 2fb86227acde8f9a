package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.testing.CastTesting.Counter;
import cast.testing.CastTesting.Pose;
import io.grpc.Status;
import java.time.Duration;
import java.util.ArrayList;
import java.util.Collections;
import java.util.HashSet;
import java.util.List;
import java.util.Map;
import java.util.Set;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.ExecutorService;
import java.util.concurrent.Executors;
import java.util.concurrent.Future;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicReference;
import org.junit.jupiter.api.AfterEach;
import org.junit.jupiter.api.BeforeEach;
import org.junit.jupiter.api.Test;

/** The component API against an in-process fake server (no real semantics needed here). */
class ComponentTest {
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

  static int counter;
  String name;
  FakeCast fake;
  final List<Component> components = new ArrayList<>();

  @BeforeEach
  void setUp() throws Exception {
    name = "fake-" + (++counter) + "-" + System.nanoTime();
    fake = new FakeCast(name, Map.of("vision", "", "motor", ""));
  }

  @AfterEach
  void tearDown() {
    for (Component c : components) {
      c.close();
    }
    fake.close();
  }

  <C extends Component> C connect(C c, String id, String sa) {
    components.add(FakeCast.connect(c, name, id, sa));
    return c;
  }

  /** Poll until {@code condition} holds; false after {@code timeout}. */
  static boolean eventually(java.util.function.BooleanSupplier condition, Duration timeout) throws InterruptedException {
    long deadline = System.nanoTime() + timeout.toNanos();
    while (!condition.getAsBoolean()) {
      if (System.nanoTime() > deadline) {
        return false;
      }
      Thread.sleep(5);
    }
    return true;
  }

  static Counter counter(String writer, long v) {
    return Counter.newBuilder().setWriter(writer).setValue(v).build();
  }

  @Test
  void readsAndWritesAreCopies() throws Exception {
    Plain c = connect(new Plain(), "c1", "vision");
    Pose.Builder b = Pose.newBuilder().setX(1).setLabel("before").addTags("a");
    c.add("p", b.build());
    b.setLabel("after").addTags("b"); // changing the writer's object later must not reach the WM
    Pose first = c.get("p", Pose.class);
    Pose second = c.get("p", Pose.class);
    assertEquals("before", first.getLabel());
    assertEquals(List.of("a"), first.getTagsList());
    assertEquals(first, second);
    assertNotSame(first, second, "every read gives a fresh object");
    Entry<Pose> e = c.getEntry("p", Pose.class);
    assertNotSame(first, e.value());
    assertEquals(new WorkingMemoryAddress("p", "vision"), e.address());
    assertEquals(0, e.version());
    assertEquals("c1", e.author());
    assertEquals("cast.testing.Pose", e.type());
  }

  @Test
  void readingWithTheWrongClassNamesBothTypes() {
    Plain c = connect(new Plain(), "c1", "vision");
    c.add("x", counter("c1", 1));
    InvalidArgumentError e = assertThrows(InvalidArgumentError.class, () -> c.get("x", Pose.class));
    assertTrue(e.getMessage().contains("cast.testing.Counter") && e.getMessage().contains("cast.testing.Pose"));
  }

  @Test
  void serverErrorsArriveAsNamedErrors() {
    Plain c = connect(new Plain(), "c1", "vision");
    c.add("x", counter("c1", 1));
    assertThrows(AlreadyExistsError.class, () -> c.add("x", counter("c1", 2)));
    assertThrows(NotFoundError.class, () -> c.get("nope", Counter.class));
    assertThrows(NotFoundError.class, () -> c.overwrite("nope", counter("c1", 2)));
    assertEquals(1, c.overwrite("x", counter("c1", 2), 0L).version());
    ConsistencyError stale = assertThrows(ConsistencyError.class, () -> c.overwrite("x", counter("c1", 3), 0L));
    assertTrue(stale.getMessage().contains("version 1"), stale.getMessage());
    assertThrows(ConsistencyError.class, () -> c.deleteEntry("x", 0L));
    assertEquals(1, c.deleteEntry("x", 1L).version());
    assertFalse(c.exists("x"));
  }

  @Test
  void newIdsAreUniqueAcrossThreadsAndComponents() throws Exception {
    Plain a = connect(new Plain(), "same", "vision");
    Plain b = connect(new Plain(), "same", "vision"); // a restart of the same component
    ExecutorService pool = Executors.newFixedThreadPool(4);
    List<Future<List<String>>> parts = new ArrayList<>();
    for (int i = 0; i < 4; i++) {
      Component c = i % 2 == 0 ? a : b;
      parts.add(
          pool.submit(
              () -> {
                List<String> ids = new ArrayList<>();
                for (int j = 0; j < 500; j++) {
                  ids.add(c.newId());
                }
                return ids;
              }));
    }
    Set<String> all = new HashSet<>();
    for (var p : parts) {
      for (String id : p.get()) {
        assertTrue(id.startsWith("same:"), id);
        assertTrue(all.add(id), "duplicate id " + id);
      }
    }
    pool.shutdown();
    assertEquals(2000, all.size());
    assertNotEquals(a.newId().split(":")[1], b.newId().split(":")[1], "restarts get another salt");
  }

  @Test
  void schemasAreRegisteredOncePerTypeBeforeTheFirstWrite() {
    Plain c = connect(new Plain(), "c1", "vision");
    assertTrue(fake.schemaRequests.isEmpty());
    c.add("a", counter("c1", 1));
    assertEquals(1, fake.schemaRequests.size());
    assertEquals("cast_testing.proto", fake.schemaRequests.get(0).getFiles().getFile(0).getName());
    c.overwrite("a", counter("c1", 2));
    c.add("b", counter("c1", 3));
    assertEquals(1, fake.schemaRequests.size(), "once per type per connection");
    c.add("p", Pose.getDefaultInstance());
    assertEquals(2, fake.schemaRequests.size());
    int registrationsBeforeRead = fake.schemaRequests.size();
    c.get("a", Counter.class);
    c.getAll(Counter.class);
    assertEquals(registrationsBeforeRead, fake.schemaRequests.size(), "reads register nothing");
  }

  @Test
  void oneComponentIsSafeToUseFromManyThreads() throws Exception {
    Plain c = connect(new Plain(), "c1", "vision");
    int threads = 8;
    int each = 50;
    ExecutorService pool = Executors.newFixedThreadPool(threads);
    CountDownLatch go = new CountDownLatch(1);
    List<Future<?>> done = new ArrayList<>();
    for (int t = 0; t < threads; t++) {
      int n = t;
      done.add(
          pool.submit(
              () -> {
                go.await();
                for (int i = 0; i < each; i++) {
                  String id = c.newId();
                  c.add(id, counter("t" + n, i));
                  assertEquals(i, c.get(id, Counter.class).getValue());
                  try (LockGuard g = c.lock(id)) {
                    c.overwrite(id, counter("t" + n, i + 1), 0L);
                  }
                }
                return null;
              }));
    }
    go.countDown(); // every thread's first write is of the same, not yet registered type
    for (Future<?> f : done) {
      f.get(30, TimeUnit.SECONDS);
    }
    pool.shutdown();
    assertEquals(1, fake.schemaRequests.size(), "the schema is registered once, before the first write");
    assertEquals(threads * each, c.getAll(Counter.class).size());
    assertTrue(fake.lockHolders.isEmpty());
  }

  @Test
  void getAllReturnsEntriesNewestFirstAsTheClassAsked() {
    Plain c = connect(new Plain(), "c1", "vision");
    c.add("a", counter("c1", 1));
    c.add("b", counter("c1", 2));
    c.add("p", Pose.getDefaultInstance());
    c.add("m", counter("c1", 9), "motor");
    List<Entry<Counter>> all = c.getAll(Counter.class);
    assertEquals(List.of("b", "a"), all.stream().map(Entry::id).toList());
    assertEquals(2, all.get(0).value().getValue());
    assertEquals(List.of("m"), c.getAll(Counter.class, "motor").stream().map(Entry::id).toList());
    assertThrows(InvalidArgumentError.class, () -> c.getAll(Counter.class, null, -1));
  }

  @Test
  void lockGuardUnlocksOnceAtTheEndOfTheBlock() {
    Plain c = connect(new Plain(), "c1", "vision");
    Plain other = connect(new Plain(), "c2", "vision");
    c.add("e", counter("c1", 1));
    LockGuard kept;
    try (LockGuard g = c.lock("e", LockMode.ODR)) {
      kept = g;
      assertEquals(new WorkingMemoryAddress("e", "vision"), g.address());
      assertEquals(1, g.depth());
      assertFalse(other.tryLock("e"), "held by c1");
      assertThrows(LockedError.class, () -> other.overwrite("e", counter("c2", 2)));
    }
    assertTrue(kept.isReleased());
    kept.close(); // idempotent: no second Unlock
    assertEquals(1, fake.calls.stream().filter(s -> s.startsWith("Unlock vision/e")).count());
    assertTrue(fake.calls.contains("Lock vision/e LOCK_MODE_ODR"), fake.calls.toString());
    assertTrue(other.tryLock("e", LockMode.O));
    assertTrue(fake.calls.contains("Lock vision/e LOCK_MODE_O nowait"), fake.calls.toString());
  }

  @Test
  void lockGuardUnlocksWhenTheBlockThrows() {
    Plain c = connect(new Plain(), "c1", "vision");
    c.add("e", counter("c1", 1));
    assertThrows(
        IllegalStateException.class,
        () -> {
          try (LockGuard g = c.lock("e")) {
            assertFalse(g.isReleased());
            throw new IllegalStateException("boom");
          }
        });
    assertNull(fake.lockHolders.get("vision/e"));
  }

  @Test
  void aBlockingLockEndsAtItsTimeout() {
    Plain c = connect(new Plain(), "c1", "vision");
    Plain other = connect(new Plain(), "c2", "vision");
    c.add("e", counter("c1", 1));
    c.lock("e");
    long t0 = System.nanoTime();
    assertThrows(DeadlineExceededError.class, () -> other.lock("e", LockMode.OD, Duration.ofMillis(300)));
    assertTrue(System.nanoTime() - t0 >= TimeUnit.MILLISECONDS.toNanos(250));
    assertEquals(0, c.unlock("e"));
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
    release.countDown();
    writer.add("after", counter("w", 2));
    assertTrue(watcher.drain(Duration.ofSeconds(5)));
    assertEquals(List.of(), got, "a cancelled watch delivers nothing, not even what was queued");
  }

  @Test
  void aStreamEndingWithOutOfRangeCallsWatchFailed() throws Exception {
    Hooks watcher = connect(new Hooks(), "watcher", "vision");
    WatchHandle h = watcher.onChange(Filters.operationFilter(), ch -> {});
    fake.failWatchStreams(Status.OUT_OF_RANGE.withDescription("revision 3 is older than the history"));
    assertTrue(watcher.watchFailedCalled.await(5, TimeUnit.SECONDS));
    assertEquals(HistoryExpiredError.class, watcher.failed.get().getClass());
    assertEquals("revision 3 is older than the history", watcher.failed.get().getMessage());
    assertSame(watcher.failed.get(), h.error());
    // Resynchronising: a new onChange opens a new stream.
    Plain writer = connect(new Plain(), "w", "vision");
    List<String> got = Collections.synchronizedList(new ArrayList<>());
    watcher.onChange(Filters.localTypeFilter(Counter.class), ch -> got.add(ch.id()));
    writer.add("again", counter("w", 1));
    assertTrue(eventually(() -> got.size() == 1, Duration.ofSeconds(5)));
    assertEquals(List.of("again"), got);
  }

  @Test
  void aBrokenWatchStreamIsOpenedAgainAndResumesAfterTheLastRevisionSeen() throws Exception {
    Plain writer = connect(new Plain(), "w", "vision");
    Plain watcher = connect(new Plain(), "watcher", "vision");
    List<Long> revisions = Collections.synchronizedList(new ArrayList<>());
    WatchHandle h = watcher.onChange(Filters.localTypeFilter(Counter.class), ch -> revisions.add(ch.revision()));
    for (int i = 0; i < 3; i++) {
      writer.add("a" + i, counter("w", i));
    }
    assertTrue(eventually(() -> revisions.size() == 3, Duration.ofSeconds(5)));
    fake.failWatchStreams(Status.UNAVAILABLE.withDescription("connection reset"));
    // The client opens the stream again and creates the watch again from revision 4, with the history id.
    assertTrue(eventually(() -> fake.creates.size() == 2, Duration.ofSeconds(10)), fake.creates.toString());
    cast.v1.WatchCreate again = fake.creates.get(1);
    assertEquals(h.watchId(), again.getWatchId());
    assertEquals(Map.of("vision", 4L), again.getStartRevisionsMap());
    assertEquals("history-1", again.getHistoryId());
    assertEquals(fake.creates.get(0).getFiltersList(), again.getFiltersList());
    writer.add("b", counter("w", 9));
    assertTrue(eventually(() -> revisions.size() == 4, Duration.ofSeconds(5)));
    assertEquals(List.of(1L, 2L, 3L, 4L), revisions);
    assertTrue(h.isActive());
    assertNull(h.error());
  }

  @Test
  void aResumeTheServerRefusesIsTheResynchroniseSignal() throws Exception {
    Hooks watcher = connect(new Hooks(), "watcher", "vision");
    WatchHandle h = watcher.onChange(Filters.operationFilter(), ch -> {});
    fake.historyId = "history-2"; // as if the server restarted without its history
    fake.failWatchStreams(Status.UNAVAILABLE.withDescription("server restarted"));
    assertTrue(watcher.watchFailedCalled.await(10, TimeUnit.SECONDS));
    assertEquals(HistoryExpiredError.class, watcher.failed.get().getClass());
    assertTrue(watcher.failed.get().getMessage().contains("resynchronise"), watcher.failed.get().getMessage());
    assertFalse(h.isActive(), "the watch that could not resume is dropped");
    assertSame(watcher.failed.get(), h.error());
  }

  @Test
  void aLostSessionIsRegisteredAgain() throws Exception {
    Plain c = connect(new Plain(), "c1", "vision");
    assertEquals(1, fake.registrations.size());
    fake.failHeartbeats(Status.UNAVAILABLE.withDescription("lease expired"));
    assertTrue(eventually(() -> fake.registrations.size() == 2, Duration.ofSeconds(10)));
    String second = name + "-session-2";
    assertTrue(eventually(() -> fake.beats.stream().anyMatch(b -> b.getSessionId().equals(second)), Duration.ofSeconds(5)));
    c.close();
    components.remove(c);
    assertTrue(eventually(() -> fake.endedSessions.contains(second), Duration.ofSeconds(5)));
  }

  @Test
  void managedComponentHooksRunOnTheDispatcher() throws Exception {
    Hooks m = connect(new Hooks(), "m", "vision");
    Task t = m.proposeTask("work", counter("m", 7), 3);
    assertEquals(TaskState.WAITING, t.state());
    assertEquals(7, t.data(Counter.class).getValue());
    m.proposeTask("reject-me");
    long deadline = System.nanoTime() + TimeUnit.SECONDS.toNanos(5);
    while (m.seen.size() < 2 && System.nanoTime() < deadline) {
      Thread.sleep(10);
    }
    assertTrue(m.drain(Duration.ofSeconds(5)));
    assertEquals(2, m.seen.size(), m.seen.toString());
    assertTrue(m.seen.get(0).startsWith("adopted work "), m.seen.toString());
    assertEquals("rejected reject-me", m.seen.get(1));
    assertTrue(fake.calls.contains("Complete t1 TASK_OUTCOME_FAILED because"), fake.calls.toString());
    m.retractTask(t);
    assertTrue(fake.calls.contains("Retract t1"));
    assertThrows(InvalidArgumentError.class, () -> m.proposeTask(""));
  }

  @Test
  void aSessionIsRegisteredKeptAliveAndEndedOnClose() throws Exception {
    Plain c = connect(new Plain(), "c1", "vision");
    assertEquals(1, fake.registrations.size());
    assertEquals("java", fake.registrations.get(0).getLanguage());
    assertEquals("unmanaged", fake.registrations.get(0).getKind());
    assertEquals(ProcessHandle.current().pid(), fake.registrations.get(0).getPid());
    // lease 300 ms: a beat every 100 ms
    Thread.sleep(450);
    assertTrue(fake.beats.size() >= 3, "beats: " + fake.beats.size());
    assertEquals(cast.v1.ComponentState.COMPONENT_STATE_STARTING, fake.beats.get(0).getState());
    c.setState(cast.v1.ComponentState.COMPONENT_STATE_RUNNING);
    Thread.sleep(250);
    assertEquals(cast.v1.ComponentState.COMPONENT_STATE_RUNNING, fake.beats.get(fake.beats.size() - 1).getState());
    c.close();
    components.remove(c);
    long deadline = System.nanoTime() + TimeUnit.SECONDS.toNanos(3);
    while (fake.endedSessions.isEmpty() && System.nanoTime() < deadline) {
      Thread.sleep(10);
    }
    assertEquals(List.of(name + "-session-1"), fake.endedSessions);
  }

  @Test
  void aStateChangeIsReportedAtOnce() throws Exception {
    fake.leaseMs = 60_000; // scheduled beats every 20 s: only the first one comes by schedule
    Plain c = connect(new Plain(), "c1", "vision");
    assertTrue(eventually(() -> fake.beats.size() == 1, Duration.ofSeconds(5)));
    c.setState(cast.v1.ComponentState.COMPONENT_STATE_RUNNING);
    assertTrue(eventually(() -> fake.beats.size() == 2, Duration.ofSeconds(5)));
    assertEquals(cast.v1.ComponentState.COMPONENT_STATE_RUNNING, fake.beats.get(1).getState());
  }

  @Test
  void anUnconnectedComponentSaysHowToConnectIt() {
    IllegalStateException e = assertThrows(IllegalStateException.class, () -> new Plain().newId());
    assertTrue(e.getMessage().contains("cast.client.Runner"), e.getMessage());
  }

  @Test
  void batchesApplyInOneCall() {
    Plain c = connect(new Plain(), "c1", "vision");
    assertEquals(List.of(), c.batch().apply());
    c.add("x", counter("c1", 0));
    Batch b = c.batch().add("y", counter("c1", 1)).overwrite("x", counter("c1", 2)).deleteEntry("x");
    assertEquals(3, b.size());
    // The fake has no Batch: the real one is tested in tests/interop; here the call reaches the server.
    CastError e = assertThrows(CastError.class, b::apply);
    assertEquals("UNIMPLEMENTED", e.code());
  }
}
