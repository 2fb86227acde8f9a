package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import com.google.protobuf.StringValue;
import java.time.Duration;
import java.util.List;
import java.util.concurrent.CopyOnWriteArrayList;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicReference;
import org.junit.jupiter.api.Test;

/**
 * The component's dispatcher thread reading its shared-memory session's socket itself while it has
 * nothing to run (docs/client-protocol.md, "A watch's events on the session's socket"), between the
 * Java client and a real server on this host ({@link RealServer}, shared memory on): blocked in the
 * socket's read, it runs each event's callback on the thread that read its frame; a call queued by
 * another thread wakes it by a NUDGE; the socket's reader thread reads while a call runs long.
 */
class DispatcherReadsTest {
  static final int MIB = SharedMemoryTest.MIB;

  /** The socket of {@code c}'s session, once its watch's first event came (the dispatcher reads it by then). */
  static SessionSocket socket(Connection c) {
    SharedSession session = SharedMemoryTest.session(c);
    assertNotNull(session, "the watcher has a session");
    return session.io();
  }

  /** {@code watcher}'s seeds of "img" (SocketEventsTest.seeds), once the first value {@code writer} adds came. */
  static List<Integer> watchFirstValue(Connection writer, Connection watcher) throws InterruptedException {
    List<Integer> got = new CopyOnWriteArrayList<>();
    watcher.onChange(Filters.addressFilter("img").withEntry(), SocketEventsTest.seeds(got));
    SocketEventsTest.write(writer, 0, 1);
    SocketEventsTest.waitForCount(got, 1);
    return got;
  }

  /** Wait until {@code d} has nothing to run and a thread reads {@code io} (the dispatcher, in its read). */
  static void waitIdleInRead(SessionSocket io, Dispatcher d, String what) throws InterruptedException {
    RealServer.waitFor(() -> io.reading() && d.pending() == 0, Duration.ofSeconds(5), what);
  }

  @Test
  void theDispatcherThreadReadsTheEventsAndRunsTheirCallbacksItself() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection watcher = server.connect("watcher", "vision", false, null)) {
      List<Integer> got = new CopyOnWriteArrayList<>();
      List<Boolean> onDispatcher = new CopyOnWriteArrayList<>();
      watcher.onChange(
          Filters.addressFilter("img").withEntry(),
          change -> {
            onDispatcher.add(watcher.onDispatcherThread());
            SocketEventsTest.seeds(got).onChange(change);
          });
      SocketEventsTest.write(writer, 0, 1);
      SocketEventsTest.waitForCount(got, 1);
      SessionSocket io = socket(watcher);
      assertSame(watcher.dispatcher(), io.dispatcher(), "the dispatcher reads the socket");
      assertSame(io, watcher.dispatcher().source());
      // From now on the reader thread stands by: every frame is read by the dispatcher thread.
      long readerBefore = io.readerReads.get();
      long dispatcherBefore = io.dispatcherReads.get();
      SocketEventsTest.write(writer, 1, 20);
      SocketEventsTest.waitForCount(got, 20);
      assertEquals(SocketEventsTest.expected(20), got);
      assertEquals(List.of(true), onDispatcher.stream().distinct().toList(), "every callback on the dispatcher thread");
      // The reader thread reads only in the place of a call that has run longer than STANDBY_MS, which a loaded
      // machine can cause by descheduling the dispatcher thread mid-call (a fresh clone's make test did, once): so
      // the dispatcher made most of the reads, not every one. How many reads it takes depends on how many frames
      // wait in the socket when it reads (several, on a loaded machine).
      long byReader = io.readerReads.get() - readerBefore;
      long byDispatcher = io.dispatcherReads.get() - dispatcherBefore;
      assertTrue(
          byDispatcher > byReader,
          "reads by the dispatcher " + byDispatcher + ", by the reader thread " + byReader);
      assertEquals(0, io.nudgesSent.get(), "nothing woke it but its frames");
      SharedMemoryTest.waitForNothingLent(server);
    }
  }

  @Test
  void aCallQueuedByAnotherThreadWakesTheDispatcherBlockedInItsReadByANudge() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection watcher = server.connect("watcher", "vision", false, null)) {
      List<Integer> got = watchFirstValue(writer, watcher);
      SessionSocket io = socket(watcher);
      Dispatcher d = watcher.dispatcher();
      waitIdleInRead(io, d, "the dispatcher idle in its read");
      for (int i = 1; i <= 3; i++) {
        AtomicReference<Thread> ranOn = new AtomicReference<>();
        CountDownLatch ran = new CountDownLatch(1);
        d.submit(
            () -> {
              ranOn.set(Thread.currentThread());
              ran.countDown();
            });
        // Nothing comes on the socket but the server's answer to the NUDGE.
        assertTrue(ran.await(5, TimeUnit.SECONDS), "the call queued by another thread ran (call " + i + ")");
        assertSame(d.thread(), ranOn.get());
        assertEquals(i, io.nudgesSent.get());
        waitIdleInRead(io, d, "the dispatcher idle again");
      }
      // The socket is still the dispatcher's, and events go on arriving in order.
      SocketEventsTest.write(writer, 1, 5);
      SocketEventsTest.waitForCount(got, 5);
      assertEquals(SocketEventsTest.expected(5), got);
    }
  }

  @Test
  void whileACallRunsLongTheReaderThreadReadsInItsPlace() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection watcher = server.connect("watcher", "vision", false, null)) {
      List<Integer> got = new CopyOnWriteArrayList<>();
      CountDownLatch release = new CountDownLatch(1);
      CountDownLatch inLongCall = new CountDownLatch(1);
      ChangeCallback seeds = SocketEventsTest.seeds(got);
      watcher.onChange(
          Filters.addressFilter("img").withEntry(),
          change -> {
            seeds.onChange(change);
            if (got.size() == 2) {
              inLongCall.countDown();
              try {
                release.await(20, TimeUnit.SECONDS);
              } catch (InterruptedException e) {
                Thread.currentThread().interrupt();
              }
            }
          });
      SocketEventsTest.write(writer, 0, 2);
      assertTrue(inLongCall.await(30, TimeUnit.SECONDS));
      SessionSocket io = socket(watcher);
      long readerBefore = io.readerReads.get();
      // Written while the callback runs: the reader thread reads them (queued, not run) after STANDBY_MS.
      SocketEventsTest.write(writer, 2, 8);
      Dispatcher d = watcher.dispatcher();
      RealServer.waitFor(() -> d.pending() >= 7, Duration.ofSeconds(10), "the values queued while the call runs");
      assertTrue(io.readerReads.get() > readerBefore, "the reader thread read while the call ran");
      assertEquals(2, got.size(), "nothing else ran meanwhile");
      release.countDown();
      SocketEventsTest.waitForCount(got, 8);
      assertEquals(SocketEventsTest.expected(8), got);
      // Back to the dispatcher: it reads the next frames itself.
      waitIdleInRead(io, d, "the dispatcher idle in its read");
      long readerAfter = io.readerReads.get();
      SocketEventsTest.write(writer, 8, 12);
      SocketEventsTest.waitForCount(got, 12);
      assertEquals(SocketEventsTest.expected(12), got);
      assertEquals(readerAfter, io.readerReads.get(), "the reader thread stands by again");
    }
  }

  @Test
  void aCallbackThatWritesReadsItsOwnReplies() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection watcher = server.connect("watcher", "vision", false, null)) {
      List<Long> echoed = new CopyOnWriteArrayList<>();
      watcher.add("echo", StringValue.of("start"));
      watcher.onChange(
          Filters.addressFilter("img").withEntry(),
          change -> {
            if (change.operation() != Operation.DELETE) {
              echoed.add(watcher.overwrite("echo", StringValue.of("seen " + change.revision())).version());
            }
          });
      SocketEventsTest.write(writer, 0, 10);
      RealServer.waitFor(() -> echoed.size() == 10, Duration.ofSeconds(30), "ten writes made in callbacks");
      assertEquals(echoed.stream().sorted().distinct().toList(), echoed, "each write answered, in order");
      assertSame(watcher.dispatcher(), socket(watcher).dispatcher());
    }
  }

  @Test
  void closingTheComponentWhileItsDispatcherWaitsInTheReadEndsPromptly() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null)) {
      Connection watcher = server.connect("watcher", "vision", false, null);
      List<Integer> got = watchFirstValue(writer, watcher);
      SessionSocket io = socket(watcher);
      Dispatcher d = watcher.dispatcher();
      waitIdleInRead(io, d, "the dispatcher idle in its read");
      long start = System.nanoTime();
      d.stop(Duration.ofSeconds(5));
      assertFalse(d.thread().isAlive(), "the dispatcher thread ended");
      assertTrue(System.nanoTime() - start < TimeUnit.SECONDS.toNanos(5), "within its stop's timeout");
      assertNull(io.dispatcher(), "the socket is its reader thread's again");
      watcher.close();
    }
  }

  @Test
  void aSocketWhoseServerDoesNotAnswerNudgesIsLeftToItsReaderThread() {
    FakeTransport t = new FakeTransport(new FakeTransport.Memory("vision"), new Identity("c", "vision", false));
    Component c = new UnmanagedComponent() {};
    c.bind(t, who -> {});
    SessionSocket old = new SessionSocket(null, "old", null, false);
    t.sink().readBy(old);
    assertNull(c.dispatcher().source(), "not read by the dispatcher: nothing could wake it in its read");
    assertNull(old.dispatcher());
    c.close();
  }
}
