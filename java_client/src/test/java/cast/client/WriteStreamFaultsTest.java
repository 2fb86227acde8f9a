package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import com.google.protobuf.Int64Value;
import java.nio.file.Files;
import java.nio.file.Path;
import java.nio.file.StandardCopyOption;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.ExecutionException;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicReference;
import org.junit.jupiter.params.ParameterizedTest;
import org.junit.jupiter.params.provider.ValueSource;

/**
 * The Write stream when things go wrong, against real servers ({@link RealServer}, one per
 * test): a server that dies fails the writes in flight with UnavailableError and the next
 * write opens a new stream; a renewed token goes on a new stream; closing waits for the
 * replies of writes in flight. Each runs with a shared-memory session, whose socket then carries
 * the writes (the stream that breaks is the session's, a renewed token opens a new session), and
 * with shared memory off, on the gRPC stream ({@code sharedMemory}).
 */
class WriteStreamFaultsTest {
  @ParameterizedTest(name = "shared memory {0}")
  @ValueSource(booleans = {true, false})
  void aBrokenStreamFailsTheWritesInFlightAndTheNextWriteOpensANewOne(boolean sharedMemory) throws Exception {
    try (RealServer server = new RealServer()) {
      RealServer.Calls calls = new RealServer.Calls();
      try (Connection holder = server.connect("holder", "vision", false, null);
          Connection waiter = server.connect("waiter", "vision", false, calls, sharedMemory)) {
        waiter.add("e", Int64Value.of(0));
        holder.lock("e", LockMode.OD);
        // A lock that waits for the holder, then writes sent to a server that no longer answers.
        AtomicReference<Throwable> lockFailure = new AtomicReference<>();
        Thread locking =
            new Thread(
                () -> {
                  try {
                    waiter.lock("e", LockMode.OD, Duration.ofSeconds(60));
                  } catch (Throwable t) {
                    lockFailure.set(t);
                  }
                });
        locking.start();
        Thread.sleep(300); // the lock request reaches the server and waits there
        server.pause();
        List<CompletableFuture<WriteResult>> inFlight = new ArrayList<>();
        for (int i = 1; i <= 3; i++) {
          inFlight.add(waiter.overwriteAsync("e", Int64Value.of(i)));
        }
        long writesByGrpcBeforeKill = calls.count("WorkingMemory/Write");
        server.kill();
        locking.join(30_000);
        assertInstanceOf(UnavailableError.class, lockFailure.get());
        String message = lockFailure.get().getMessage();
        String broke =
            sharedMemory
                ? "the shared-memory session with " + server.endpoint() + " ended ("
                : "the write stream to " + server.endpoint() + " broke (";
        assertTrue(message.startsWith(broke), message);
        assertTrue(message.contains("may or may not have been applied"), message);
        for (CompletableFuture<WriteResult> f : inFlight) {
          ExecutionException e = assertThrows(ExecutionException.class, () -> f.get(30, TimeUnit.SECONDS));
          assertInstanceOf(UnavailableError.class, e.getCause());
          assertTrue(e.getCause().getMessage().startsWith(broke), e.getCause().getMessage());
        }
        // The same address again, an empty memory: the next write that gets through is on a new stream.
        server.restart();
        RealServer.waitFor(
            () -> {
              try {
                waiter.add("after", Int64Value.of(1));
                return true;
              } catch (UnavailableError e) {
                return false; // the channel is still connecting
              }
            },
            Duration.ofSeconds(30),
            "a write after the restart");
        assertEquals(1, waiter.get("after", Int64Value.class).getValue());
        if (sharedMemory) { // the session's socket carried the writes; after the restart a new session, or gRPC meanwhile
          assertEquals(0, writesByGrpcBeforeKill, calls.methods.toString());
        } else {
          assertTrue(calls.count("WorkingMemory/Write") >= 2, calls.methods.toString());
        }
      }
    }
  }

  @ParameterizedTest(name = "shared memory {0}")
  @ValueSource(booleans = {true, false})
  void aRenewedTokenGoesOnANewStreamAndARefusedWriteIsSentOnceMoreWithIt(boolean sharedMemory) throws Exception {
    try (RealServer server = new RealServer()) {
      long expires = System.currentTimeMillis() / 1000 + 4; // time to connect both and write once
      // "open": its stream is open before the token expires; "late": its first write comes after.
      Path openFile = Files.createTempFile("cast-junit-token", "");
      Path lateFile = Files.createTempFile("cast-junit-token", "");
      Files.writeString(openFile, RealServer.token("open", "vision", false, expires));
      Files.writeString(lateFile, RealServer.token("late", "vision", false, expires));
      RealServer.Calls openCalls = new RealServer.Calls();
      RealServer.Calls lateCalls = new RealServer.Calls();
      try (Connection open =
              server.connect(
                  new LaunchContract(server.endpoint(), "open", "vision", "", Args.empty(), null, openFile.toString()),
                  openCalls,
                  sharedMemory);
          Connection late =
              server.connect(
                  new LaunchContract(server.endpoint(), "late", "vision", "", Args.empty(), null, lateFile.toString()),
                  lateCalls,
                  sharedMemory)) {
        open.add("t", Int64Value.of(1));
        SharedSession first = SharedMemoryTest.transport(open).server("vision").shared.current();
        assertEquals(sharedMemory, first != null, "a session with shared memory on, none without");
        RealServer.waitFor(
            () -> System.currentTimeMillis() / 1000.0 > expires + 0.3, Duration.ofSeconds(10), "the tokens to expire");
        // "late" opens its stream now (a delete registers no schema first): the server refuses the whole call.
        UnauthenticatedError refused = assertThrows(UnauthenticatedError.class, () -> late.deleteEntry("t"));
        assertTrue(refused.getMessage().contains("expired"), refused.getMessage());
        // Renewed as the orchestrator does (write and rename). The file was just checked, so the
        // next write goes with the old token, is refused, and goes again on a new stream.
        renew(lateFile, RealServer.token("late", "vision", false, 0));
        late.deleteEntry("t");
        assertFalse(late.exists("t"));
        // "open": a request on its open stream is refused alone; then the same with the renewed token.
        UnauthenticatedError expired =
            assertThrows(UnauthenticatedError.class, () -> open.add("t", Int64Value.of(2)));
        assertTrue(expired.getMessage().contains("expired"), expired.getMessage());
        String renewed = RealServer.token("open", "vision", false, 0);
        renew(openFile, renewed);
        open.add("t", Int64Value.of(3));
        assertEquals(3, late.get("t", Int64Value.class).getValue());
        if (sharedMemory) {
          // Its writes went on its session's socket; the renewed token on a new session, whose HELLO carried it.
          assertEquals(0, openCalls.count("WorkingMemory/Write"), openCalls.methods.toString());
          SharedSession second = SharedMemoryTest.transport(open).server("vision").shared.current();
          assertNotSame(first, second);
          assertNotNull(first.dead(), "the old session ended");
          assertEquals(renewed, second.token);
          assertEquals(1, second.writes().framesSent.get(), "the write sent again went on the new session");
          // "late" had no session (its expired token could not ask for one), so the gRPC stream; unless
          // a session could be opened by the time of its write with the renewed token.
          assertTrue(lateCalls.count("WorkingMemory/Write") >= 2 || RealServer.writeFrames(late) >= 1,
              lateCalls.methods.toString());
        } else {
          assertEquals(2, openCalls.count("WorkingMemory/Write"), openCalls.methods.toString());
          // Three calls when the retry used the old token once more (the file is checked at most
          // once a second), two when the write came more than a second after the refusal.
          assertTrue(lateCalls.count("WorkingMemory/Write") >= 2, lateCalls.methods.toString());
        }
      } finally {
        Files.deleteIfExists(openFile);
        Files.deleteIfExists(lateFile);
      }
    }
  }

  private static void renew(Path file, String token) throws java.io.IOException {
    Path next = file.resolveSibling(file.getFileName() + ".new");
    Files.writeString(next, token);
    Files.move(next, file, StandardCopyOption.REPLACE_EXISTING, StandardCopyOption.ATOMIC_MOVE);
  }

  @ParameterizedTest(name = "shared memory {0}")
  @ValueSource(booleans = {true, false})
  void closingWaitsForTheRepliesOfWritesInFlightAndRefusesLaterOnes(boolean sharedMemory) throws Exception {
    try (RealServer server = new RealServer()) {
      Connection wm = server.connect("closer", "vision", false, null, sharedMemory);
      wm.add("c", Int64Value.of(0));
      List<CompletableFuture<WriteResult>> inFlight = new ArrayList<>();
      for (int i = 1; i <= 100; i++) {
        inFlight.add(wm.overwriteAsync("c", Int64Value.of(i)));
      }
      wm.close();
      for (CompletableFuture<WriteResult> f : inFlight) {
        assertNotNull(f.get(10, TimeUnit.SECONDS), "answered before the stream closed");
      }
      UnavailableError closed = assertThrows(UnavailableError.class, () -> wm.add("d", Int64Value.of(1)));
      assertTrue(closed.getMessage().contains("is closed"), closed.getMessage());
      try (Connection reader = server.connect("reader", "vision", false, null)) {
        assertEquals(100, reader.get("c", Int64Value.class).getValue());
      }
    }
  }
}
