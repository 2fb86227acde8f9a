package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import com.google.protobuf.BytesValue;
import com.google.protobuf.ByteString;
import com.google.protobuf.Int64Value;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.Random;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.CopyOnWriteArrayList;
import java.util.concurrent.ExecutionException;
import java.util.concurrent.TimeUnit;
import org.junit.jupiter.api.AfterAll;
import org.junit.jupiter.api.BeforeAll;
import org.junit.jupiter.api.Test;
import org.junit.jupiter.api.TestInstance;
import org.junit.jupiter.params.ParameterizedTest;
import org.junit.jupiter.params.provider.ValueSource;

/**
 * The Write stream against a real server ({@link RealServer}): every write and lock of a
 * component goes on one WorkingMemory.Write call per server, with the results and the named
 * errors of the unary calls; addAsync/overwriteAsync keep many writes in flight in call
 * order; values of 1 MiB and more travel both ways and to a watcher. What happens when the
 * stream breaks, or the token is renewed: {@link WriteStreamFaultsTest}. With a shared-memory
 * session (on the server's host, as here) the same requests go on the session's socket instead
 * (docs/client-protocol.md, "Writes on the session's socket"): the tests that say which transport
 * carried them run once with shared memory and once without ({@code sharedMemory}); the others
 * run on the socket ({@link SocketWritesTest} has its own).
 */
@TestInstance(TestInstance.Lifecycle.PER_CLASS)
class WriteStreamTest {
  private RealServer server;

  @BeforeAll
  void startServer() throws Exception {
    server = new RealServer();
  }

  @AfterAll
  void stopServer() throws Exception {
    server.close();
  }

  @ParameterizedTest(name = "shared memory {0}")
  @ValueSource(booleans = {true, false})
  void everyWriteAndLockGoesOnOneWriteStreamAndAGetOnTheSessionsSocketIfAny(boolean sharedMemory) throws Exception {
    RealServer.Calls calls = new RealServer.Calls();
    long frames;
    try (Connection wm = server.connect("streamer-" + sharedMemory, "vision", false, calls, sharedMemory)) {
      WriteResult added = wm.add("s1", Int64Value.of(1));
      WriteResult overwritten = wm.overwrite("s1", Int64Value.of(2), added.version());
      assertEquals(added.revision() + 1, overwritten.revision());
      assertTrue(overwritten.version() > added.version());
      List<WriteResult> batch =
          wm.batch().add("s2", Int64Value.of(3)).overwrite("s1", Int64Value.of(4), overwritten.version())
              .deleteEntry("s2").apply();
      assertEquals(3, batch.size());
      assertEquals(overwritten.revision() + 3, batch.get(2).revision());
      try (LockGuard guard = wm.lock("s1", LockMode.OD, Duration.ofSeconds(5))) {
        assertTrue(wm.tryLock("s1"), "re-entrant");
        assertEquals(1, wm.unlock("s1"), "one level released, one held");
      }
      WriteResult deleted = wm.deleteEntry("s1");
      assertEquals(batch.get(1).version(), deleted.version(), "a delete answers the version the entry had");
      assertFalse(wm.exists("s1"));
      assertThrows(NotFoundError.class, () -> wm.get("s1", Int64Value.class));
      frames = RealServer.writeFrames(wm);
    }
    // Eight requests: add, overwrite, batch, lock, tryLock, unlock, the guard's unlock, delete; and
    // with a session the get too, on its socket (SocketReadsTest), else the unary Get.
    if (sharedMemory) {
      assertEquals(0, calls.count("WorkingMemory/Write"), calls.methods.toString());
      assertEquals(9, frames, "a WRITES frame each on the session's socket");
      assertEquals(0, calls.count("WorkingMemory/Get"));
    } else {
      assertEquals(1, calls.count("WorkingMemory/Write"), calls.methods.toString());
      assertEquals(0, frames);
      assertEquals(1, calls.count("WorkingMemory/Get"));
    }
    for (String unary : List.of("Add", "Overwrite", "Delete", "Batch", "Lock", "Unlock")) {
      assertEquals(0, calls.count("WorkingMemory/" + unary), unary + " went unary: " + calls.methods);
    }
    assertEquals(1, calls.count("WorkingMemory/Exists"));
  }

  @Test
  void refusalsOnTheStreamAreTheNamedErrorsOfTheUnaryCallsAndChangeNothing() throws Exception {
    try (Connection wm = server.connect("refused", "vision", false, null);
        Connection holder = server.connect("holder", "vision", false, null)) {
      WriteResult r1 = wm.add("r1", Int64Value.of(1));
      AlreadyExistsError exists = assertThrows(AlreadyExistsError.class, () -> wm.add("r1", Int64Value.of(2)));
      assertTrue(exists.getMessage().startsWith("entry 'r1' already exists in subarchitecture 'vision'"), exists.getMessage());
      ConsistencyError stale =
          assertThrows(ConsistencyError.class, () -> wm.overwrite("r1", Int64Value.of(2), r1.version() + 7));
      assertTrue(stale.getMessage().contains("expected " + (r1.version() + 7)), stale.getMessage());
      assertThrows(NotFoundError.class, () -> wm.overwrite("no-such-entry", Int64Value.of(2)));
      PermissionDeniedError denied =
          assertThrows(PermissionDeniedError.class, () -> wm.add("x", Int64Value.of(1), "motor"));
      assertTrue(denied.getMessage().contains("may not add in subarchitecture 'motor'"), denied.getMessage());
      // A refused batch names the failing operation and applies none of them.
      AlreadyExistsError inBatch =
          assertThrows(AlreadyExistsError.class, () -> wm.batch().add("b1", Int64Value.of(1)).add("r1", Int64Value.of(1)).apply());
      assertTrue(inBatch.getMessage().startsWith("batch operation 1: "), inBatch.getMessage());
      assertFalse(wm.exists("b1"));
      // Another component's lock: writes refused naming the holder, tryLock false, a timed lock times out.
      try (LockGuard held = holder.lock("r1", LockMode.O)) {
        LockedError locked = assertThrows(LockedError.class, () -> wm.overwrite("r1", Int64Value.of(3)));
        assertTrue(locked.getMessage().contains("holder"), locked.getMessage());
        assertFalse(wm.tryLock("r1"));
        DeadlineExceededError waited =
            assertThrows(DeadlineExceededError.class, () -> wm.lock("r1", LockMode.OD, Duration.ofMillis(300)));
        assertEquals("DEADLINE_EXCEEDED", waited.code());
      }
      assertEquals(1, wm.get("r1", Int64Value.class).getValue(), "nothing refused was applied");
      // The precise class the server names (the unary calls' cast-error trailer): a lock without a session.
      try (GrpcTransport bare =
          new GrpcTransport(
              new LaunchContract(server.endpoint(), "bare", "vision", RealServer.token("bare", "vision", false, 0),
                  Args.empty()))) {
        NoSessionError none =
            assertThrows(NoSessionError.class, () -> bare.lock("vision", "r1", LockMode.OD, null, true));
        assertEquals("FAILED_PRECONDITION", none.code());
      }
    }
  }

  @ParameterizedTest(name = "shared memory {0}")
  @ValueSource(booleans = {true, false})
  void asyncWritesArePipelinedInCallOrderAndTheirRefusalsArriveOnTheirFutures(boolean sharedMemory) throws Exception {
    RealServer.Calls calls = new RealServer.Calls();
    long frames;
    try (Connection wm = server.connect("pipeliner-" + sharedMemory, "vision", false, calls, sharedMemory)) {
      String p = sharedMemory ? "p-shm-" : "p-grpc-"; // the entries of each run its own
      WriteResult first = wm.add(p + "1", Int64Value.of(0));
      int messagesBefore = calls.writeMessages.get();
      List<CompletableFuture<WriteResult>> inFlight = new ArrayList<>();
      for (int i = 1; i <= 200; i++) {
        inFlight.add(wm.overwriteAsync(p + "1", Int64Value.of(i)));
      }
      CompletableFuture<WriteResult> taken = wm.addAsync(p + "1", Int64Value.of(-1));
      CompletableFuture<WriteResult> stale = wm.overwriteAsync(p + "1", Int64Value.of(-2), first.version());
      long revision = first.revision();
      for (CompletableFuture<WriteResult> f : inFlight) {
        assertEquals(++revision, f.get(60, TimeUnit.SECONDS).revision(), "applied in call order");
      }
      if (!sharedMemory) {
        // What queued up while a message was sent went together in the next: fewer messages than writes
        // (how many fewer depends on the machine's load; one message per write is what must not be).
        int messages = calls.writeMessages.get() - messagesBefore;
        assertTrue(messages < 202, messages + " messages for 202 writes");
      }
      ExecutionException e = assertThrows(ExecutionException.class, () -> taken.get(60, TimeUnit.SECONDS));
      assertInstanceOf(AlreadyExistsError.class, e.getCause());
      e = assertThrows(ExecutionException.class, () -> stale.get(60, TimeUnit.SECONDS));
      assertInstanceOf(ConsistencyError.class, e.getCause());
      assertEquals(200, wm.get(p + "1", Int64Value.class).getValue());
      // A continuation may write synchronously: it does not run on the thread that reads the replies.
      WriteResult chained =
          wm.addAsync(p + "2", Int64Value.of(1))
              .thenApply(r -> wm.overwrite(p + "2", Int64Value.of(2), r.version()))
              .get(60, TimeUnit.SECONDS);
      assertTrue(chained.version() > 0 || chained.revision() > 0);
      assertEquals(2, wm.get(p + "2", Int64Value.class).getValue());
      frames = RealServer.writeFrames(wm);
    }
    assertEquals(sharedMemory ? 0 : 1, calls.count("WorkingMemory/Write"), calls.methods.toString());
    // 205 writes and the 2 gets (SocketReadsTest).
    assertEquals(sharedMemory ? 207 : 0, frames, "every write in a WRITES frame on the session's socket, or none");
  }

  @ParameterizedTest(name = "shared memory {0}")
  @ValueSource(booleans = {true, false})
  void manyThreadsWriteAtOnceOnTheOneStream(boolean sharedMemory) throws Exception {
    RealServer.Calls calls = new RealServer.Calls();
    long frames;
    try (Connection wm = server.connect("threads-" + sharedMemory, "motor", false, calls, sharedMemory)) {
      String w = sharedMemory ? "w-shm-" : "w-grpc-"; // the entries of each run its own
      List<Thread> writers = new ArrayList<>();
      List<Long> revisions = new CopyOnWriteArrayList<>();
      List<Throwable> failures = new CopyOnWriteArrayList<>();
      for (int t = 0; t < 4; t++) {
        int thread = t;
        writers.add(new Thread(() -> {
          try {
            for (int i = 0; i < 100; i++) {
              revisions.add(wm.add(w + thread + "-" + i, Int64Value.of(i)).revision());
              if (i % 10 == 0) {
                revisions.add(wm.overwriteAsync(w + thread + "-" + i, Int64Value.of(-i)).get().revision());
              }
            }
          } catch (Throwable e) {
            failures.add(e);
          }
        }));
      }
      writers.forEach(Thread::start);
      for (Thread t : writers) {
        t.join(60_000);
      }
      assertEquals(List.of(), failures);
      assertEquals(440, revisions.stream().distinct().count(), "every write applied once");
      assertEquals(-90, wm.get(w + "3-90", Int64Value.class).getValue());
      frames = RealServer.writeFrames(wm);
    }
    assertEquals(sharedMemory ? 0 : 1, calls.count("WorkingMemory/Write"), calls.methods.toString());
    // 440 writes and the get (SocketReadsTest).
    assertEquals(sharedMemory ? 441 : 0, frames, "every write in a WRITES frame on the session's socket, or none");
  }

  @Test
  void aValueOfOneAndAHalfMebibytesIsWrittenReadBackAndWatched() throws Exception {
    byte[] bytes = new byte[1536 * 1024];
    new Random(19).nextBytes(bytes);
    BytesValue image = BytesValue.of(ByteString.copyFrom(bytes));
    try (Connection writer = server.connect("imager", "vision", false, null);
        Connection viewer = server.connect("viewer", "vision", false, null)) {
      List<WorkingMemoryChange> seen = new CopyOnWriteArrayList<>();
      viewer.onChange(Filters.addressFilter(new WorkingMemoryAddress("image", "vision")).withEntry(), seen::add);
      writer.add("image", image);
      assertEquals(image, writer.get("image", BytesValue.class));
      // Ten more frames in flight at once: more than gRPC takes at a time, so they queue up.
      List<CompletableFuture<WriteResult>> frames = new ArrayList<>();
      for (int i = 1; i <= 10; i++) {
        bytes[0] = (byte) i;
        frames.add(writer.overwriteAsync("image", BytesValue.of(ByteString.copyFrom(bytes))));
      }
      CompletableFuture.allOf(frames.toArray(new CompletableFuture<?>[0])).get(60, TimeUnit.SECONDS);
      RealServer.waitFor(() -> seen.size() == 11, Duration.ofSeconds(60), "11 changes of the image");
      assertEquals(image, seen.get(0).entry(BytesValue.class).value());
      ByteString last = seen.get(10).entry(BytesValue.class).value().getValue();
      assertEquals(bytes.length, last.size());
      assertEquals(10, last.byteAt(0));
      assertEquals(ByteString.copyFrom(bytes), last);
      // Past the server's limit for one value: refused naming the limit; past gRPC's, never sent.
      InvalidArgumentError tooBig =
          assertThrows(InvalidArgumentError.class, () -> writer.overwrite("image", BytesValue.of(ByteString.copyFrom(new byte[9 << 20]))));
      assertTrue(tooBig.getMessage().contains("limits.max_value_bytes"), tooBig.getMessage());
      CompletableFuture<WriteResult> huge =
          writer.overwriteAsync("image", BytesValue.of(ByteString.copyFrom(new byte[65 << 20])));
      ExecutionException overGrpc = assertThrows(ExecutionException.class, () -> huge.get(60, TimeUnit.SECONDS));
      assertInstanceOf(InvalidArgumentError.class, overGrpc.getCause());
      assertTrue(overGrpc.getCause().getMessage().contains("over the gRPC message limit of 67108864 bytes"),
          overGrpc.getCause().getMessage());
      assertEquals(ByteString.copyFrom(bytes), writer.get("image", BytesValue.class).getValue(), "the stream goes on");
    }
  }
}
