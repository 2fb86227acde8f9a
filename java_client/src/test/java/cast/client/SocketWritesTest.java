package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import com.google.protobuf.ByteString;
import com.google.protobuf.BytesValue;
import java.lang.reflect.Field;
import java.nio.file.Files;
import java.nio.file.Path;
import java.nio.file.StandardCopyOption;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.CopyOnWriteArrayList;
import java.util.concurrent.ExecutionException;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicReference;
import org.junit.jupiter.api.AfterAll;
import org.junit.jupiter.api.BeforeAll;
import org.junit.jupiter.api.Test;
import org.junit.jupiter.api.TestInstance;
import org.newsclub.net.unix.AFUNIXSocket;

/**
 * Writes on the shared-memory session's socket ({@link SessionWrites}) against a real server on
 * this host ({@link RealServer}): a Java component with a session sends every write there
 * (docs/client-protocol.md, "Writes on the session's socket"), none on the gRPC Write stream. A
 * mix of staged and small values, waited for and pipelined, is applied once each in call order;
 * a thread that waits for its write reads the reply itself until a pipelined write needs the
 * reader thread, which reads again when the writes pause; a lock request waiting on the server is
 * read for by the reader thread, so that its thread can be interrupted, and the session lives on;
 * pipelined writes outstanding when the component closes are answered first; a socket that ends
 * under outstanding writes fails them with UnavailableError naming the session, and later writes
 * succeed; a write past its deadline fails with DeadlineExceededError and ends the session, failing
 * the others; a large value written after the token was renewed is staged in the new session it
 * goes on; a callback that writes while its dispatcher's queue is full gets its reply, and so does
 * an async write's continuation that writes and waits. The twin
 * of cpp_client/tests/server/socket_writes_test.cc. (The Write stream's own tests,
 * WriteStreamTest and WriteStreamFaultsTest, run on the socket too, and again with shared memory
 * off.)
 */
@TestInstance(TestInstance.Lifecycle.PER_CLASS)
class SocketWritesTest {
  static final int MIB = SharedMemoryTest.MIB;
  private RealServer shared; // the tests that end no session share it

  @BeforeAll
  void startServer() throws Exception {
    shared = new RealServer();
  }

  @AfterAll
  void stopServer() throws Exception {
    shared.close();
  }

  static BytesValue value(int size, int seed) {
    byte[] b = new byte[size];
    java.util.Arrays.fill(b, (byte) ('a' + seed % 26));
    b[0] = (byte) seed; // values of the same size and letter differ
    return BytesValue.newBuilder().setValue(ByteString.copyFrom(b)).build();
  }

  /**
   * The server sees {@code session}'s socket end, as when the connection drops, and ends the
   * session: the client learns it by reading the socket's end, not by closing it itself.
   */
  static void endSocket(SharedSession session) throws Exception {
    Field f = SharedSession.class.getDeclaredField("socket");
    f.setAccessible(true);
    ((AFUNIXSocket) f.get(session)).shutdownOutput(); // the server reads the end, ends the session and closes
  }

  @Test
  void aMixOfStagedAndSmallValuesWaitedForAndPipelinedIsAppliedOnceInCallOrder() throws Exception {
    RealServer.Calls calls = new RealServer.Calls();
    long stagedBefore = SharedMemoryTest.metrics(shared).getStagedWrites();
    try (Connection writer = shared.connect("sw-writer", "vision", false, calls);
        Connection watcher = shared.connect("sw-watcher", "vision", false, null)) {
      List<long[]> seen = new CopyOnWriteArrayList<>(); // {version, index of the value}
      List<BytesValue> values = new ArrayList<>();
      for (int i = 0; i < 24; i++) {
        values.add(value(i % 3 == 0 ? MIB : 16 + i, i)); // staged and small
      }
      watcher.onChange(
          Filters.addressFilter("sw-x").withEntry(),
          change -> {
            if (change.operation() != Operation.DELETE) {
              BytesValue got = change.entry(BytesValue.class).value();
              seen.add(new long[] {change.version(), values.indexOf(got)});
            }
          });
      SharedSession session = SharedMemoryTest.session(writer);
      assertNotNull(session, "the writer has a session");
      List<Long> versions = new ArrayList<>();
      versions.add(writer.add("sw-x", values.get(0)).version());
      List<CompletableFuture<WriteResult>> pipelined = new ArrayList<>();
      for (int i = 1; i < values.size(); i++) {
        if (i % 4 == 0) {
          for (CompletableFuture<WriteResult> f : pipelined) {
            versions.add(f.get(30, TimeUnit.SECONDS).version());
          }
          pipelined.clear();
          versions.add(writer.overwrite("sw-x", values.get(i)).version());
        } else {
          pipelined.add(writer.overwriteAsync("sw-x", values.get(i)));
        }
      }
      for (CompletableFuture<WriteResult> f : pipelined) {
        versions.add(f.get(30, TimeUnit.SECONDS).version());
      }
      RealServer.waitFor(() -> seen.size() >= values.size(), Duration.ofSeconds(30), "every change (got " + seen.size() + ")");
      Thread.sleep(200); // nothing more comes: each was applied once
      assertEquals(values.size(), seen.size());
      for (int i = 0; i < values.size(); i++) {
        assertEquals(versions.get(i), seen.get(i)[0], "write " + i);
        assertEquals(i, seen.get(i)[1], "write " + i);
      }
      long written = session.writes().framesSent.get(); // the get goes in a frame on the session too
      assertEquals(values.get(values.size() - 1), writer.get("sw-x", BytesValue.class));
      // They went on the session's socket, a WRITES frame each, the large ones staged; none by gRPC.
      assertEquals(values.size(), written);
      assertSame(session, SharedMemoryTest.session(writer), "the same session throughout");
      assertEquals(0, calls.count("WorkingMemory/Write"), calls.methods.toString());
      assertEquals(0, calls.count("WorkingMemory/Add") + calls.count("WorkingMemory/Overwrite"));
      assertEquals(8, SharedMemoryTest.metrics(shared).getStagedWrites() - stagedBefore);
    }
  }

  @Test
  void aThreadThatWaitsForItsWriteReadsTheReplyItselfUntilSomethingNeedsTheReader() throws Exception {
    try (Connection writer = shared.connect("sw-own-reply", "vision", false, null)) {
      SharedSession session = SharedMemoryTest.session(writer);
      assertNotNull(session);
      Thread.sleep(SessionSocket.WRITER_PAUSE_MS * 2); // the reader thread reads: no write came yet
      for (int i = 0; i < 50; i++) {
        writer.add("sw-own" + i, value(i % 10 == 0 ? MIB : 8, i));
      }
      // The first reply may be read by the reader thread (it held the socket); it then leaves the
      // socket to the writer while the writes come.
      assertTrue(session.io().waiterReads.get() >= 40, "reads by the waiting writer: " + session.io().waiterReads.get());
      // Each read asks for about what comes (a reply), not the whole 64 KiB buffer, which junixsocket would copy.
      long reads = session.io().waiterReads.get() + session.io().readerReads.get() + session.io().dispatcherReads.get();
      long asked = session.io().bytesAsked.get();
      assertTrue(asked <= reads * SessionSocket.SMALL_READ, asked + " bytes asked in " + reads + " reads");
      assertFalse(session.io().readsAlways());
      // Once the writes pause, the reader thread reads again: the server's end is noticed with no write.
      Thread.sleep(SessionSocket.WRITER_PAUSE_MS * 3);
      assertTrue(session.io().reading(), "the reader thread waits on the socket");
      assertNotNull(writer.addAsync("sw-own-async", value(8, 1)).get(10, TimeUnit.SECONDS));
      assertTrue(session.io().readsAlways(), "a write nobody waits for: the reader thread reads all the time");
      for (int i = 0; i < 10; i++) { // answered by whichever thread reads: the reader thread, mostly
        writer.overwrite("sw-own" + i, value(8, i + 1));
      }
      assertEquals(value(8, 10), writer.get("sw-own9", BytesValue.class));
    }
  }

  @Test
  void pipelinedWritesOutstandingWhenTheComponentClosesAreAnsweredFirst() throws Exception {
    Connection writer = shared.connect("sw-closer", "vision", false, null);
    SharedSession session = SharedMemoryTest.session(writer);
    assertNotNull(session);
    List<CompletableFuture<WriteResult>> adds = new ArrayList<>();
    for (int i = 0; i < 100; i++) {
      adds.add(writer.addAsync("sw-c" + i, value(i % 2 == 1 ? MIB : 8, i)));
    }
    writer.close(); // the session ends once its outstanding writes were answered
    for (CompletableFuture<WriteResult> f : adds) {
      assertNotNull(f.get(10, TimeUnit.SECONDS), "answered before the session ended");
    }
    assertEquals(100, session.writes().framesSent.get(), "they went on the session's socket");
    assertNotNull(session.dead(), "the session ended with the component");
    try (Connection reader = shared.connect("sw-close-reader", "vision", false, null)) {
      assertTrue(reader.exists("sw-c99"));
      assertEquals(value(MIB, 99), reader.get("sw-c99", BytesValue.class));
    }
  }

  @Test
  void anInterruptedLockRequestIsCancelledAndTheSessionLivesOn() throws Exception {
    try (Connection holder = shared.connect("sw-int-holder", "vision", false, null);
        Connection waiter = shared.connect("sw-int-waiter", "vision", false, null)) {
      holder.add("sw-int", value(8, 1));
      LockGuard held = holder.lock("sw-int");
      SharedSession session = SharedMemoryTest.session(waiter);
      assertNotNull(session);
      AtomicReference<Throwable> failed = new AtomicReference<>();
      Thread waiting =
          new Thread(
              () -> {
                try {
                  for (int i = 0; i < 5; i++) { // writes waited for: the reader thread leaves the socket to them
                    waiter.add("sw-int-before" + i, value(8, i));
                  }
                  waiter.lock("sw-int", LockMode.OD).close();
                  failed.set(new AssertionError("granted"));
                } catch (Throwable t) {
                  failed.set(t);
                }
              });
      waiting.start();
      Thread.sleep(300); // the lock request waits on the server; its thread reads the socket for the reply
      assertTrue(session.io().reading());
      long reads = session.io().waiterReads.get();
      assertTrue(reads >= 3, "the waiting writer reads the socket itself: " + reads);
      waiting.interrupt();
      waiting.join(20_000);
      assertNotNull(failed.get(), "the interrupted writer returned");
      assertInstanceOf(CastError.class, failed.get());
      assertEquals("CANCELLED", ((CastError) failed.get()).code(), failed.get().getMessage());
      // A lock's waiting thread does not read the socket (a read cannot be interrupted): the reader thread does.
      assertEquals(reads, session.io().waiterReads.get(), "the lock's waiting thread did not read");
      assertNull(session.dead(), "the session lives on");
      // Another lock request waits, and is granted once the holder lets go: the reader thread read its reply.
      AtomicReference<Throwable> second = new AtomicReference<>();
      Thread granted =
          new Thread(
              () -> {
                try (LockGuard g = waiter.lock("sw-int", LockMode.OD)) {
                  second.set(null);
                } catch (Throwable t) {
                  second.set(t);
                }
              });
      second.set(new AssertionError("not granted yet"));
      granted.start();
      Thread.sleep(200);
      held.close();
      granted.join(20_000);
      assertNull(second.get(), "the second lock request was granted");
      waiter.add("sw-int-after", value(8, 2));
      assertSame(session, SharedMemoryTest.session(waiter));
      assertEquals(value(8, 2), holder.get("sw-int-after", BytesValue.class));
    }
  }

  @Test
  void aSocketThatEndsFailsTheOutstandingWritesAsUnavailableAndLaterWritesSucceed() throws Exception {
    try (RealServer server = new RealServer(); // its own: a session of it is ended here
        Connection holder = server.connect("sw-holder", "vision", false, null);
        Connection waiter = server.connect("sw-waiter", "vision", false, null)) {
      holder.add("sw-l", value(8, 1));
      LockGuard held = holder.lock("sw-l");
      SharedSession first = SharedMemoryTest.session(waiter);
      assertNotNull(first);
      AtomicReference<Throwable> failed = new AtomicReference<>();
      Thread waiting =
          new Thread(
              () -> {
                try {
                  waiter.lock("sw-l", LockMode.OD).close();
                  failed.set(new AssertionError("granted"));
                } catch (Throwable t) {
                  failed.set(t);
                }
              });
      waiting.start();
      Thread.sleep(300); // the lock request reaches the server and waits there
      assertEquals(1, first.writes().outstanding(), "the lock waits, on the socket");
      endSocket(first);
      waiting.join(20_000);
      assertInstanceOf(UnavailableError.class, failed.get());
      String message = failed.get().getMessage();
      assertTrue(message.contains("the shared-memory session with " + server.endpoint() + " ended"), message);
      assertTrue(message.contains("may or may not have been applied"), message);
      // Later writes succeed, on a new session (the server is there), in order, large ones too.
      BytesValue big = value(MIB, 2);
      RealServer.waitFor(
          () -> {
            try {
              waiter.add("sw-after", value(8, 3));
              return true;
            } catch (UnavailableError e) {
              return false;
            }
          },
          Duration.ofSeconds(20),
          "a write after the socket ended");
      waiter.overwrite("sw-after", big);
      assertEquals(big, holder.get("sw-after", BytesValue.class));
      SharedSession second = SharedMemoryTest.session(waiter);
      assertNotSame(first, second);
      assertEquals(2, second.writes().framesSent.get(), "the later writes went on the new session");
      held.close();
    }
  }

  @Test
  void aWritePastItsDeadlineFailsAndEndsTheSessionWhoseOtherWritesFailAsUnavailable() throws Exception {
    try (RealServer server = new RealServer(); // its own: it is stopped here
        Connection writer = server.connect("sw-late", "vision", false, null)) {
      try {
        writer.add("sw-d", value(8, 0));
        SharedSession session = SharedMemoryTest.session(writer);
        server.pause(); // takes the requests into its socket, answers none
        CompletableFuture<WriteResult> inFlight = writer.overwriteAsync("sw-d", value(8, 1)); // due in 30 s
        long start = System.nanoTime();
        // Its deadline (0.5 s and the reply's margin) comes long before the one already watched.
        DeadlineExceededError late =
            assertThrows(DeadlineExceededError.class, () -> writer.lock("sw-d", LockMode.OD, Duration.ofMillis(500)));
        assertTrue(System.nanoTime() - start < TimeUnit.SECONDS.toNanos(10), "it failed by its deadline");
        assertTrue(late.getMessage().startsWith("no reply from " + server.endpoint() + " to the lock of 'sw-d' within"
            + " 1.5 s on the shared-memory session: it may or may not have been applied"), late.getMessage());
        ExecutionException other = assertThrows(ExecutionException.class, () -> inFlight.get(10, TimeUnit.SECONDS));
        assertInstanceOf(UnavailableError.class, other.getCause());
        assertTrue(other.getCause().getMessage().startsWith("the shared-memory session with " + server.endpoint()
            + " ended (" + server.endpoint() + " answered no write on the shared-memory session within its deadline"),
            other.getCause().getMessage());
        assertNotNull(session.dead(), "the session was ended");
        assertEquals(0, session.writes().outstanding());
      } finally {
        server.kill();
      }
    }
  }

  @Test
  void aLargeWriteAfterTheTokenWasRenewedIsStagedInTheNewSessionItGoesOn() throws Exception {
    Path file = Files.createTempFile("cast-junit-token", "");
    try {
      renew(file, RealServer.token("sw-renewed", "vision", false, 0));
      try (Connection writer =
              shared.connect(
                  new LaunchContract(shared.endpoint(), "sw-renewed", "vision", "", Args.empty(), null, file.toString()),
                  null);
          Connection reader = shared.connect("sw-renewed-reader", "vision", false, null)) {
        long stagedBefore = SharedMemoryTest.metrics(shared).getStagedWrites();
        writer.add("sw-r", value(MIB, 1));
        SharedSession first = SharedMemoryTest.transport(writer).server("vision").shared.current();
        Thread.sleep(1100); // a token issued later differs; the file is looked at once a second
        String renewed = RealServer.token("sw-renewed", "vision", false, 0);
        renew(file, renewed);
        // Staged in a session opened with the new token, the one the write then goes on: staged in the
        // old one, which the write's renewal ends, the server would refuse it (its session is gone).
        BytesValue big = value(MIB, 2);
        writer.overwrite("sw-r", big);
        assertEquals(big, reader.get("sw-r", BytesValue.class));
        SharedSession second = SharedMemoryTest.transport(writer).server("vision").shared.current();
        assertNotSame(first, second);
        assertNotNull(first.dead(), "the old session ended");
        assertEquals(renewed, second.token);
        assertEquals(1, second.writes().framesSent.get());
        assertEquals(2, SharedMemoryTest.metrics(shared).getStagedWrites() - stagedBefore, "both staged");
      }
    } finally {
      Files.deleteIfExists(file);
    }
  }

  /** Replaces the token file whole, as the orchestrator renews it (write, then rename). */
  static void renew(Path file, String token) throws java.io.IOException {
    Path next = file.resolveSibling(file.getFileName() + ".new");
    Files.writeString(next, token);
    Files.move(next, file, StandardCopyOption.REPLACE_EXISTING, StandardCopyOption.ATOMIC_MOVE);
  }

  @Test
  void aCallbackThatWritesWhileItsQueueIsFullGetsItsReply() throws Exception {
    // The reader thread, holding an event for the full queue, reads on while a write waits for its
    // REPLIES frame: the waiting write may be the callback that keeps the queue full.
    try (Connection writer = shared.connect("sw-source", "vision", false, null);
        SocketEventsTest.Small echo = new SocketEventsTest.Small(shared, "sw-echo", 1)) {
      List<Long> echoed = new CopyOnWriteArrayList<>();
      List<Throwable> failures = new CopyOnWriteArrayList<>();
      echo.onChange(
          Filters.addressFilter("sw-src").withEntry(),
          change -> {
            try {
              echoed.add(echo.overwrite("sw-echoed", change.entry(BytesValue.class).value()).version());
            } catch (Throwable t) {
              failures.add(t);
            }
          });
      echo.add("sw-echoed", value(8, 0));
      writer.add("sw-src", value(8, 0));
      // Pipelined, so that the events come faster than the callbacks' writes are answered.
      List<CompletableFuture<WriteResult>> burst = new ArrayList<>();
      for (int i = 1; i < 40; i++) {
        burst.add(writer.overwriteAsync("sw-src", value(i % 4 == 0 ? MIB : 8, i)));
      }
      CompletableFuture.allOf(burst.toArray(new CompletableFuture<?>[0])).get(30, TimeUnit.SECONDS);
      // Each callback's write answered (a write past its deadline would fail, after 30 s), in order.
      RealServer.waitFor(
          () -> !failures.isEmpty() || echoed.size() == 40, Duration.ofSeconds(25), "40 writes by the callback");
      assertEquals(List.of(), failures);
      SharedSession session = ((GrpcTransport) echo.transport()).server("vision").shared.current();
      assertEquals(41, session.writes().framesSent.get(), "the add and the callbacks' writes, on the socket");
      assertEquals(value(8, 39), echo.get("sw-echoed", BytesValue.class));
    }
  }

  @Test
  void aContinuationOfAnAsyncWriteThatWritesAndWaitsGetsItsReply() throws Exception {
    // The futures of addAsync/overwriteAsync complete on the component's results thread, not the
    // session's reader: a continuation's own write is read by the reader meanwhile.
    try (Connection writer = shared.connect("sw-then", "vision", false, null)) {
      writer.add("sw-then-e", value(8, 0));
      CompletableFuture<long[]> both =
          writer
              .overwriteAsync("sw-then-e", value(8, 1))
              .thenApply(
                  first ->
                      new long[] {
                        first.version(), writer.overwrite("sw-then-e", value(8, 2)).version()
                      });
      // A write nobody reads would fail after its deadline (30 s).
      long[] versions = both.get(30, TimeUnit.SECONDS);
      assertTrue(versions[1] > versions[0]);
      assertEquals(value(8, 2), writer.get("sw-then-e", BytesValue.class));
      SharedSession session = SharedMemoryTest.session(writer);
      assertNotNull(session);
      assertNull(session.dead(), "the session lives on: no write of it passed its deadline");
    }
  }
}
