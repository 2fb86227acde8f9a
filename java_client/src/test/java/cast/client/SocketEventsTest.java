package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.v1.SharedValue;
import com.google.protobuf.BytesValue;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.concurrent.CopyOnWriteArrayList;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicReference;
import org.junit.jupiter.api.Test;

/**
 * A watch's events on the session's socket (docs/client-protocol.md, "A watch's events on the
 * session's socket"), between the Java client and a real server on this host ({@link
 * RealServer}, shared memory on): a Java watch with a session asks for its event batches as
 * EVENTS frames, which the session's reader thread queues on the dispatcher.
 */
class SocketEventsTest {
  static final int MIB = SharedMemoryTest.MIB;

  /** A component with a small dispatcher queue (the client's capacity is reached at once). */
  static final class Small extends UnmanagedComponent {
    private final int capacity;

    Small(RealServer server, String id, int capacity) {
      this.capacity = capacity;
      GrpcTransport transport =
          new GrpcTransport(
              new LaunchContract(server.endpoint(), id, "vision", RealServer.token(id, "vision", false, 0), Args.empty()),
              e -> GrpcServer.channel(e, null, new io.grpc.ClientInterceptor[0]),
              GrpcTransport.DEFAULT_CALL_TIMEOUT);
      bind(transport, who -> {});
      setState(ComponentState.RUNNING);
    }

    @Override
    protected int maxPendingCallbacks() {
      return capacity;
    }
  }

  /** The first byte of each value's image, as the callbacks saw them (image(MIB, seed) starts with seed % 251). */
  static ChangeCallback seeds(List<Integer> got) {
    return change -> {
      if (change.operation() != Operation.DELETE) {
        try (ValueView view = change.view()) {
          assertTrue(view.isShared(), "a MiB value is lent by shared memory");
          got.add(Byte.toUnsignedInt(view.field(1).get(0)));
        }
      }
    };
  }

  static void write(Component writer, int from, int to) {
    for (int seed = from; seed < to; seed++) {
      if (seed == 0) {
        writer.add("img", SharedMemoryTest.image(MIB, 0));
      } else {
        writer.overwrite("img", SharedMemoryTest.image(MIB, seed));
      }
    }
  }

  static List<Integer> expected(int count) {
    List<Integer> out = new ArrayList<>();
    for (int seed = 0; seed < count; seed++) {
      out.add(seed % 251);
    }
    return out;
  }

  static void waitForCount(List<Integer> got, int count) throws InterruptedException {
    RealServer.waitFor(() -> got.size() >= count, Duration.ofSeconds(30), count + " values (got " + got.size() + ")");
  }

  @Test
  void aWatchsEventsComeAsFramesOnTheSessionsSocketEachOnceInOrder() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection watcher = server.connect("watcher", "vision", false, null)) {
      List<Integer> got = new CopyOnWriteArrayList<>();
      watcher.onChange(Filters.addressFilter("img").withEntry(), seeds(got));
      SharedSession session = SharedMemoryTest.session(watcher);
      assertNotNull(session, "the watcher has a session");
      write(writer, 0, 20);
      waitForCount(got, 20);
      assertEquals(expected(20), got);
      // Every event came in an EVENTS frame (one or more per batch), none on the gRPC call's messages.
      assertTrue(session.eventFrames.get() >= 1, "EVENTS frames read: " + session.eventFrames.get());
      SharedMemoryTest.waitForNothingLent(server); // each view given back, each value RECEIVED and released
    }
  }

  @Test
  void smallValuesComeInTheFramesAsBytes() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection watcher = server.connect("watcher", "vision", false, null)) {
      List<String> got = new CopyOnWriteArrayList<>();
      watcher.onChange(
          Filters.addressFilter("small").withEntry(),
          change -> got.add(change.entry(BytesValue.class).value().getValue().toStringUtf8()));
      SharedSession session = SharedMemoryTest.session(watcher);
      for (String v : List.of("a", "b", "c")) {
        BytesValue value = BytesValue.newBuilder().setValue(com.google.protobuf.ByteString.copyFromUtf8(v)).build();
        if (v.equals("a")) {
          writer.add("small", value);
        } else {
          writer.overwrite("small", value);
        }
      }
      RealServer.waitFor(() -> got.size() == 3, Duration.ofSeconds(30), "three small values");
      assertEquals(List.of("a", "b", "c"), got);
      assertTrue(session.eventFrames.get() >= 1, "EVENTS frames read: " + session.eventFrames.get());
    }
  }

  @Test
  void aWatchWhoseSocketEndsResumesOnANewSessionWithoutGapOrDuplicate() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection watcher = server.connect("watcher", "vision", false, null)) {
      List<Integer> got = new CopyOnWriteArrayList<>();
      watcher.onChange(Filters.addressFilter("img").withEntry(), seeds(got));
      SharedSession first = SharedMemoryTest.session(watcher);
      write(writer, 0, 10);
      waitForCount(got, 10);
      first.end("ended by the test"); // the socket closes: the server ends the call, the client resumes
      write(writer, 10, 40);
      waitForCount(got, 40);
      assertEquals(expected(40), got); // in order, each once
      assertTrue(SharedMemoryTest.transport(watcher).watchReconnects() >= 1, "the call was opened again");
      SharedSession second = SharedMemoryTest.session(watcher);
      assertNotSame(first, second);
      assertTrue(second.eventFrames.get() >= 1, "the resumed call's events came as frames on the new session");
      SharedMemoryTest.waitForNothingLent(server); // what the old session held, the server took back
    }
  }

  @Test
  void aSlowCallbackLagsOnlyItsOwnWatchAndGetsEveryValueOnceInOrder() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection other = server.connect("other", "vision", false, null);
        Small slow = new Small(server, "slow", 2)) {
      CountDownLatch go = new CountDownLatch(1);
      List<Integer> slowGot = new CopyOnWriteArrayList<>();
      ChangeCallback seeds = seeds(slowGot);
      slow.onChange(
          Filters.addressFilter("img").withEntry(),
          change -> {
            try {
              assertTrue(go.await(60, TimeUnit.SECONDS));
            } catch (InterruptedException e) {
              Thread.currentThread().interrupt();
            }
            seeds.onChange(change);
          });
      List<Integer> otherGot = new CopyOnWriteArrayList<>();
      other.onChange(Filters.addressFilter("img").withEntry(), seeds(otherGot));
      SharedSession session = ((GrpcTransport) slow.transport()).server("vision").shared.session();
      write(writer, 0, 30); // every write acknowledged while the slow callback holds its queue full
      waitForCount(otherGot, 30); // and the other watcher got every value meanwhile
      assertEquals(List.of(), slowGot);
      go.countDown();
      waitForCount(slowGot, 30);
      assertEquals(expected(30), slowGot);
      assertEquals(expected(30), otherGot);
      assertTrue(session.eventFrames.get() >= 1);
    }
  }

  @Test
  void aClaimWaitingForItsSegmentIsSeenByTheReader() throws Exception {
    try (RealServer server = new RealServer();
        Connection watcher = server.connect("watcher", "vision", false, null)) {
      SharedSession session = SharedMemoryTest.session(watcher);
      assertFalse(session.segmentAwaited());
      AtomicReference<Throwable> failed = new AtomicReference<>();
      Thread claimer =
          new Thread(
              () -> {
                try {
                  session.newCall().claim(SharedValue.newBuilder().setSegment(999).setSize(10).setValueId(1).build());
                } catch (Throwable t) {
                  failed.set(t);
                }
              });
      claimer.start();
      RealServer.waitFor(session::segmentAwaited, Duration.ofSeconds(4), "a thread waiting for segment 999");
      session.end("ended by the test"); // the waiting claim gives up
      claimer.join(5000);
      assertInstanceOf(UnavailableError.class, failed.get());
      assertFalse(session.segmentAwaited());
    }
  }

  @Test
  void aFullDispatcherQueuesTheReadersChangeOverItsCapacityOnlyWhileOverflowHolds() throws Exception {
    Dispatcher d = new Dispatcher("overflow", 1, DispatcherTest.LOG);
    FakeTransport t = new FakeTransport(new FakeTransport.Memory("vision"), new Identity("c", "vision", false));
    List<Long> ran = new CopyOnWriteArrayList<>();
    int watchId = d.watch(t, List.of(Filters.addressFilter(new WorkingMemoryAddress("img", "vision"))), c -> ran.add(c.revision()), WatchOptions.queue()).watchId();
    CountDownLatch gate = new CountDownLatch(1);
    d.submit(
        () -> {
          try {
            gate.await(10, TimeUnit.SECONDS);
          } catch (InterruptedException e) {
            Thread.currentThread().interrupt();
          }
        }); // the queue is full
    java.util.concurrent.atomic.AtomicBoolean segmentAwaited = new java.util.concurrent.atomic.AtomicBoolean();
    CountDownLatch queued = new CountDownLatch(1);
    Thread reader =
        new Thread(
            () -> {
              d.deliver(change(1, watchId), segmentAwaited::get);
              queued.countDown();
            });
    reader.start();
    assertFalse(queued.await(300, TimeUnit.MILLISECONDS), "the reader waits for room while no segment is awaited");
    segmentAwaited.set(true);
    assertTrue(queued.await(5, TimeUnit.SECONDS), "then it queues over the capacity");
    assertEquals(2, d.pending());
    gate.countDown();
    assertTrue(d.drain(Duration.ofSeconds(5)));
    assertEquals(List.of(1L), ran);
    d.stop(Duration.ofSeconds(1));
  }

  private static Transport.Change change(long revision, int watchId) {
    return new Transport.Change(revision, Operation.OVERWRITE, new WorkingMemoryAddress("img", "vision"),
        "google.protobuf.BytesValue", revision, "w", "vision", java.time.Instant.EPOCH, null, List.of(watchId));
  }
}
