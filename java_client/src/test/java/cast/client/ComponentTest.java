package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.testing.CastTesting.Counter;
import cast.testing.CastTesting.Pose;
import java.time.Duration;
import java.util.ArrayList;
import java.util.HashSet;
import java.util.List;
import java.util.Set;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.ExecutorService;
import java.util.concurrent.Executors;
import java.util.concurrent.Future;
import java.util.concurrent.TimeUnit;
import org.junit.jupiter.api.Test;

/**
 * The working-memory calls of the component API (writes, reads, ids, schemas, locks,
 * batches) against the in-memory fake transport: what the component sends and how it
 * turns the answers and refusals into values and named errors. The server's own rules
 * are tested against a real server in tests/interop.
 */
class ComponentTest extends WithFakeMemory {
  static final class Plain extends UnmanagedComponent {}

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
    assertTrue(memory.schemaRequests.isEmpty());
    c.add("a", counter("c1", 1));
    assertEquals(1, memory.schemaRequests.size());
    assertEquals("cast_testing.proto", memory.schemaRequests.get(0).getFile(0).getName());
    c.overwrite("a", counter("c1", 2));
    c.add("b", counter("c1", 3));
    assertEquals(1, memory.schemaRequests.size(), "once per type per connection");
    c.add("p", Pose.getDefaultInstance());
    assertEquals(2, memory.schemaRequests.size());
    int registrationsBeforeRead = memory.schemaRequests.size();
    c.get("a", Counter.class);
    c.getAll(Counter.class);
    assertEquals(registrationsBeforeRead, memory.schemaRequests.size(), "reads register nothing");
  }

  @Test
  void aTypeIsRegisteredWithTheServerOfEachSaItIsWrittenToAndNoOther() {
    Plain c = new Plain();
    c.bind(new FakeTransport(memory, new Identity("p", "vision", true)), who -> {});
    c.add("a", counter("p", 1));
    c.add("a", counter("p", 1), "motor");
    c.overwrite("a", counter("p", 2), "motor");
    c.batch("motor").add("b", counter("p", 3)).apply();
    c.add("p", Pose.getDefaultInstance(), "motor");
    assertEquals(List.of("vision", "motor", "motor"), memory.schemaSas);
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
    assertEquals(1, memory.schemaRequests.size(), "the schema is registered once, before the first write");
    assertEquals(threads * each, c.getAll(Counter.class).size());
    assertTrue(memory.lockHolders.isEmpty());
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
    assertEquals(1, memory.calls.stream().filter(s -> s.startsWith("Unlock vision/e")).count());
    assertTrue(memory.calls.contains("Lock vision/e ODR"), memory.calls.toString());
    assertTrue(other.tryLock("e", LockMode.O));
    assertTrue(memory.calls.contains("Lock vision/e O nowait"), memory.calls.toString());
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
    assertNull(memory.lockHolders.get("vision/e"));
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
  void anUnconnectedComponentSaysHowToConnectIt() {
    IllegalStateException e = assertThrows(IllegalStateException.class, () -> new Plain().newId());
    assertTrue(e.getMessage().contains("cast.client.Runner"), e.getMessage());
  }

  @Test
  void batchesApplyInOneCall() {
    Plain c = connect(new Plain(), "c1", "vision");
    assertEquals(List.of(), c.batch().apply());
    assertTrue(FakeTransport.of(c).batches.isEmpty(), "an empty batch sends nothing");
    c.add("x", counter("c1", 0));
    Batch b = c.batch().add("y", counter("c1", 1)).overwrite("x", counter("c1", 2), 0L).deleteEntry("x");
    assertEquals(3, b.size());
    List<WriteResult> results = b.apply();
    // One call with the writes in order, each value registered and packed like a single write's.
    List<Transport.Write> sent = FakeTransport.of(c).batches.get(0);
    assertEquals(1, FakeTransport.of(c).batches.size());
    assertEquals(
        List.of(Operation.ADD, Operation.OVERWRITE, Operation.DELETE), sent.stream().map(Transport.Write::operation).toList());
    assertEquals(List.of("y", "x", "x"), sent.stream().map(Transport.Write::id).toList());
    assertEquals(Types.pack(counter("c1", 2)), sent.get(1).value());
    assertEquals(0L, sent.get(1).expectedVersion());
    assertNull(sent.get(2).value());
    assertEquals(List.of(0L, 1L, 1L), results.stream().map(WriteResult::version).toList());
    assertEquals(List.of("y"), c.getAll(Counter.class).stream().map(Entry::id).toList());
  }
}
