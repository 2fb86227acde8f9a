package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.v1.DescribeSystemRequest;
import cast.v1.DirectoryGrpc;
import cast.v1.GetMetricsRequest;
import cast.v1.GetRequest;
import cast.v1.InspectionGrpc;
import cast.v1.OverwriteRequest;
import cast.v1.SharedMemoryInfo;
import cast.v1.SharedMemoryMetrics;
import cast.v1.StagedValue;
import cast.v1.WorkingMemoryGrpc;
import com.google.protobuf.Any;
import com.google.protobuf.ByteString;
import com.google.protobuf.BytesValue;
import io.grpc.ManagedChannel;
import io.grpc.ManagedChannelBuilder;
import io.grpc.Metadata;
import io.grpc.Status;
import io.grpc.StatusRuntimeException;
import io.grpc.stub.AbstractStub;
import io.grpc.stub.MetadataUtils;
import java.io.IOException;
import java.io.RandomAccessFile;
import java.nio.ByteBuffer;
import java.nio.MappedByteBuffer;
import java.nio.ReadOnlyBufferException;
import java.nio.channels.FileChannel;
import java.nio.file.Files;
import java.nio.file.Path;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.concurrent.CopyOnWriteArrayList;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.TimeUnit;
import java.util.logging.Handler;
import java.util.logging.LogRecord;
import java.util.logging.Logger;
import org.junit.jupiter.api.Test;

/**
 * Large values by shared memory between the Java client and a real server on this host
 * (docs/client-protocol.md, "Large values by shared memory"): {@link RealServer} runs {@code
 * cast serve} with shared memory on (the default), the components are {@link Connection}s over
 * the real transport in this JVM. What the server refuses is met here by requests built by hand,
 * as a client that misbehaves would send them.
 */
class SharedMemoryTest {
  static final int MIB = 1 << 20;

  static BytesValue image(int size, int seed) {
    byte[] b = new byte[size];
    for (int i = 0; i < size; i++) {
      b[i] = (byte) ((seed + i) % 251);
    }
    return BytesValue.newBuilder().setValue(ByteString.copyFrom(b)).build();
  }

  /** The server's shared-memory figures. */
  static SharedMemoryMetrics metrics(RealServer server) {
    ManagedChannel channel = ManagedChannelBuilder.forTarget(server.endpoint()).usePlaintext().build();
    try {
      return authorised(InspectionGrpc.newBlockingStub(channel), "t")
          .getMetrics(GetMetricsRequest.getDefaultInstance())
          .getSharedMemory();
    } finally {
      channel.shutdownNow();
    }
  }

  static <S extends AbstractStub<S>> S authorised(S stub, String component) {
    Metadata md = new Metadata();
    md.put(
        Metadata.Key.of("authorization", Metadata.ASCII_STRING_MARSHALLER),
        "Bearer " + RealServer.token(component, "vision", false, 0));
    return stub.withInterceptors(MetadataUtils.newAttachHeadersInterceptor(md));
  }

  static GrpcTransport transport(Connection c) {
    return (GrpcTransport) c.transport();
  }

  /** The session of a connection with the server of SA vision (opened now if it can be). */
  static SharedSession session(Connection c) {
    return transport(c).server("vision").shared.session();
  }

  static void waitForNothingLent(RealServer server) throws InterruptedException {
    RealServer.waitFor(() -> metrics(server).getLentBytes() == 0, Duration.ofSeconds(20), "every value given back");
  }

  @Test
  void largeValuesGoByReferenceToReadersOnTheHostAndReadBackIdentical() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection reader = server.connect("reader", "vision", false, null)) {
      List<String> seen = new CopyOnWriteArrayList<>();
      CountDownLatch three = new CountDownLatch(3);
      reader.onChange(
          Filters.addressFilter("img").withEntry(),
          change -> {
            try (ValueView view = change.view()) {
              BytesValue decoded = change.entry(BytesValue.class).value();
              seen.add(change.revision() + " " + decoded.getValue().equals(ByteString.copyFrom(view.field(1)))
                  + " " + view.isShared());
            }
            three.countDown();
          });
      List<BytesValue> frames = List.of(image(MIB, 0), image(MIB, 1), image(MIB, 2));
      writer.add("img", frames.get(0));
      writer.overwrite("img", frames.get(1));
      writer.overwriteAsync("img", frames.get(2)).get(30, TimeUnit.SECONDS);
      writer.add("small", BytesValue.newBuilder().setValue(ByteString.copyFromUtf8("tiny")).build());
      assertTrue(three.await(30, TimeUnit.SECONDS), seen.toString());
      assertEquals(List.of("1 true true", "2 true true", "3 true true"), seen);
      assertEquals(frames.get(2), reader.get("img", BytesValue.class));
      assertEquals(frames.get(2), reader.getEntry("img", BytesValue.class).value());
      List<Entry<BytesValue>> all = reader.getAll(BytesValue.class);
      assertEquals(List.of("tiny", "big"), all.stream().map(e -> e.value().getValue().size() < 10 ? "tiny" : "big").toList());
      assertEquals(frames.get(2), all.get(1).value());
      try (ValueView view = reader.getView("img")) {
        assertTrue(view.isShared());
        assertEquals("google.protobuf.BytesValue", view.type());
        assertEquals(writer.getEntry("img", BytesValue.class).version(), view.version());
        assertEquals("writer", view.author());
        assertEquals(ByteBuffer.wrap(frames.get(2).getValue().toByteArray()), view.field(1)); // the pixels, not copied
        // ... starting on a cache line: the server's arena aligns a value's largest bytes field.
        assertEquals(0, view.field(1).alignmentOffset(0, 64));
        assertEquals(frames.get(2), view.decode(BytesValue.class));
        assertEquals(frames.get(2).getSerializedSize(), view.size());
      }
      try (ValueView view = reader.getView("small")) {
        assertFalse(view.isShared());
        assertEquals(ByteBuffer.wrap(BytesValue.newBuilder().setValue(ByteString.copyFromUtf8("tiny")).build()
            .toByteArray()), view.data());
      }
      SharedMemoryMetrics m = metrics(server);
      assertEquals(3, m.getStagedWrites()); // the Java writer staged them
      assertTrue(m.getLent() >= 6, m.toString()); // three events, a get, a getEntry, a getAll, a view
      assertEquals(2, m.getSessions());
      waitForNothingLent(server);
    }
  }

  @Test
  void aReaderCannotWriteWhatItWasLentNorTheMemoryFileItCameIn() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection reader = server.connect("reader", "vision", false, null)) {
      writer.add("img", image(MIB, 3));
      try (ValueView view = reader.getView("img")) {
        assertTrue(view.isShared());
        assertThrows(ReadOnlyBufferException.class, () -> view.data().put(0, (byte) 1));
        assertThrows(ReadOnlyBufferException.class, () -> view.field(1).put((byte) 1));
        // The memory file itself, opened again read-write by its path: no write, no writable mapping.
        List<Path> segments = mapped("arena");
        assertFalse(segments.isEmpty());
        for (Path segment : segments) {
          try (RandomAccessFile file = new RandomAccessFile(segment.toFile(), "rw")) {
            ByteBuffer one = ByteBuffer.wrap(new byte[] {1});
            IOException write = assertThrows(IOException.class, () -> file.getChannel().write(one, 0));
            assertTrue(write.getMessage().contains("Operation not permitted"), write.getMessage());
            assertThrows(IOException.class, () -> file.getChannel().map(FileChannel.MapMode.READ_WRITE, 0, 4096));
          }
        }
      }
      assertEquals(image(MIB, 3), reader.get("img", BytesValue.class));
    }
  }

  /** The server's memory files of one kind ("arena", "staging") this process maps, by their /proc/self/map_files paths. */
  static List<Path> mapped(String kind) throws IOException {
    List<Path> out = new ArrayList<>();
    for (String line : Files.readAllLines(Path.of("/proc/self/maps"))) {
      if (line.contains("memfd:cast-" + kind)) {
        out.add(Path.of("/proc/self/map_files/" + line.split(" ")[0]));
      }
    }
    return out;
  }

  @Test
  void aDeadServersMemoryIsUnmappedOnceNoValueOfItIsHeld() throws Exception {
    RealServer server = new RealServer();
    List<Path> arenas = mapped("arena"); // of other tests' servers in this JVM, if any are still mapped
    List<Path> areas = mapped("staging");
    try (Connection writer = server.connect("writer", "vision", false, null);
        Connection reader = server.connect("reader", "vision", false, null)) {
      writer.add("img", image(MIB, 4));
      assertEquals(image(MIB, 4), reader.get("img", BytesValue.class)); // lent, decoded, given back
      ValueView held = reader.getView("img");
      assertTrue(held.isShared());
      assertEquals(arenas.size() + 1, mapped("arena").size());
      assertEquals(areas.size() + 2, mapped("staging").size());
      server.kill();
      // The sessions end with the server: their staging areas go at once, the segment once the view is closed.
      RealServer.waitFor(
          () -> uncheckedMapped("staging").size() == areas.size(), Duration.ofSeconds(20), "the staging areas unmapped");
      assertEquals(arenas.size() + 1, mapped("arena").size());
      assertEquals(ByteBuffer.wrap(image(MIB, 4).getValue().toByteArray()), held.field(1)); // still there, unchanged
      held.close();
      assertEquals(arenas, mapped("arena"));
    } finally {
      server.close();
    }
  }

  static List<Path> uncheckedMapped(String kind) {
    try {
      return mapped(kind);
    } catch (IOException e) {
      throw new AssertionError(e);
    }
  }

  @Test
  void aWriterCannotChangeAValueAfterItsWriteWasAcknowledged() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection reader = server.connect("reader", "vision", false, null)) {
      List<ByteString> seen = new CopyOnWriteArrayList<>();
      reader.onChange(
          Filters.addressFilter("img").withEntry(), change -> seen.add(change.entry(BytesValue.class).value().getValue()));
      BytesValue original = image(MIB, 5);
      writer.add("img", original); // acknowledged
      // The writer still has its staging area mapped writable: it writes over all of it.
      List<Path> staging = mapped("staging");
      assertFalse(staging.isEmpty());
      for (Path area : staging) {
        try (RandomAccessFile file = new RandomAccessFile(area.toFile(), "rw")) {
          MappedByteBuffer map = file.getChannel().map(FileChannel.MapMode.READ_WRITE, 0, file.length());
          while (map.hasRemaining()) {
            map.put((byte) 0xFF);
          }
        }
      }
      RealServer.waitFor(() -> !seen.isEmpty(), Duration.ofSeconds(20), "the event");
      assertEquals(original.getValue(), seen.get(0));
      assertEquals(original, reader.get("img", BytesValue.class));
      assertEquals(original, writer.get("img", BytesValue.class));
    }
  }

  @Test
  void forgedAndStaleReferencesAreRefusedWithAClearErrorAndChangeNothing() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null)) {
      writer.add("img", image(MIB, 1));
      Entry<BytesValue> before = writer.getEntry("img", BytesValue.class);
      ManagedChannel channel = ManagedChannelBuilder.forTarget(server.endpoint()).usePlaintext().build();
      try {
        SharedMemoryInfo info =
            authorised(DirectoryGrpc.newBlockingStub(channel), "writer")
                .describeSystem(DescribeSystemRequest.getDefaultInstance())
                .getSharedMemory();
        SharedSession raw = SharedLink.connect(info, RealServer.token("writer", "vision", false, 0), server.endpoint());
        Any value = Types.pack(image(MIB, 7));
        ShmStaging.Staged staged = raw.stage(value.getValue());
        StagedValue good = raw.stagedValue(staged);
        Status.Code invalid = Status.Code.INVALID_ARGUMENT;
        StagedValue forgedSession = good.toBuilder().setSession(ByteString.copyFrom(new byte[16])).build();
        String forged = refused(channel, "writer", forgedSession, value, invalid);
        assertTrue(forged.contains("which this server does not have"), forged);
        String outside = refused(channel, "writer", good.toBuilder().setOffset(1L << 40).build(), value, invalid);
        assertTrue(outside.contains("outside the staging area"), outside);
        String over = refused(channel, "writer", good.toBuilder().setSize(9L * MIB).build(), value, invalid);
        assertTrue(over.contains("limits.max_value_bytes"), over);
        String other = refused(channel, "other", good, value, Status.Code.PERMISSION_DENIED);
        assertTrue(other.contains("may not use the shared-memory session"), other);
        raw.end("closed by the test");
        RealServer.waitFor(() -> metrics(server).getSessions() == 1, Duration.ofSeconds(20), "the raw session's end");
        String stale = refused(channel, "writer", good, value, invalid);
        assertTrue(stale.contains("which this server does not have"), stale);
        // A read naming a session by forged metadata: malformed, or another component's.
        GetRequest get = GetRequest.newBuilder().setAddress(Conversions.address("vision", "img")).build();
        SharedSession mine = session(writer);
        for (String bad : List.of("nothex/1", mine.idHex + "/1")) {
          Metadata md = new Metadata();
          md.put(SharedLink.METADATA_KEY, bad);
          StatusRuntimeException e =
              assertThrows(
                  StatusRuntimeException.class,
                  () -> authorised(WorkingMemoryGrpc.newBlockingStub(channel), "other")
                      .withInterceptors(MetadataUtils.newAttachHeadersInterceptor(md))
                      .get(get));
          assertEquals(bad.startsWith("nothex") ? Status.Code.INVALID_ARGUMENT : Status.Code.PERMISSION_DENIED,
              e.getStatus().getCode());
        }
      } finally {
        channel.shutdownNow();
      }
      Entry<BytesValue> after = writer.getEntry("img", BytesValue.class);
      assertEquals(before, after); // nothing changed
    }
  }

  /** An overwrite of "img" as {@code who} naming {@code staged}, refused with {@code code}: its message. */
  private static String refused(ManagedChannel channel, String who, StagedValue staged, Any value, Status.Code code) {
    OverwriteRequest request =
        OverwriteRequest.newBuilder()
            .setAddress(Conversions.address("vision", "img"))
            .setValue(Conversions.typeOnly(value))
            .setStagedValue(staged)
            .build();
    StatusRuntimeException e =
        assertThrows(
            StatusRuntimeException.class, () -> authorised(WorkingMemoryGrpc.newBlockingStub(channel), who).overwrite(request));
    assertEquals(code, e.getStatus().getCode(), e.getStatus().toString());
    return e.getStatus().getDescription();
  }

  @Test
  void callbacksReadLentValuesAndAViewHoldsOnePastItsCallback() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection reader = server.connect("reader", "vision", false, null)) {
      List<WorkingMemoryChange> changes = new CopyOnWriteArrayList<>();
      List<ValueView> views = new CopyOnWriteArrayList<>();
      reader.onChange(
          Filters.addressFilter("img").withEntry(),
          change -> {
            changes.add(change);
            views.add(change.view()); // a view only: the change keeps no copy
          });
      writer.add("img", image(MIB, 0));
      writer.overwrite("img", image(MIB, 1));
      RealServer.waitFor(() -> views.size() == 2, Duration.ofSeconds(20), "two events");
      assertTrue(reader.drain(Duration.ofSeconds(10)));
      // The callbacks returned: their holds went back, the views hold the values still.
      for (int k = 0; k < 2; k++) {
        ValueView view = views.get(k);
        assertTrue(view.isShared());
        assertEquals(ByteBuffer.wrap(image(MIB, (int) view.revision() - 1).getValue().toByteArray()), view.field(1));
      }
      assertEquals(2L * image(MIB, 0).getSerializedSize(), metrics(server).getLentBytes());
      views.forEach(ValueView::close);
      InvalidArgumentError released = assertThrows(InvalidArgumentError.class, () -> views.get(0).field(1));
      assertTrue(released.getMessage().contains("was released"), released.getMessage());
      // A callback that took a view keeps no copy: once the views are closed the change has nothing to read.
      InvalidArgumentError gone = assertThrows(InvalidArgumentError.class, () -> changes.get(0).entry(BytesValue.class));
      assertTrue(gone.getMessage().contains("read it through that view"), gone.getMessage());
      waitForNothingLent(server);
    }
  }

  @Test
  void aCallbacksValuesAreGivenBackByTheDispatcherThreadItself() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection reader = server.connect("reader", "vision", false, null)) {
      List<Long> sums = new CopyOnWriteArrayList<>();
      reader.onChange(
          Filters.addressFilter("img").withEntry(),
          change -> {
            long sum = 0;
            try (ValueView view = change.view()) { // closed: the value goes back as the callback returns
              for (ByteBuffer b = view.field(1); b.hasRemaining(); ) {
                sum += b.get();
              }
            }
            sums.add(sum);
          });
      writer.add("img", image(MIB, 0));
      for (int i = 1; i < 20; i++) {
        writer.overwrite("img", image(MIB, i));
      }
      RealServer.waitFor(() -> sums.size() == 20, Duration.ofSeconds(20), "twenty events");
      waitForNothingLent(server);
      SharedSession session = session(reader);
      // No other thread of the reader writes on its socket but the sender's rare RECEIVED: each
      // RELEASE went from the thread that let the value go, with no hand-off to the sender thread.
      assertTrue(session.io().releasesInline.get() >= 15, "inline " + session.io().releasesInline.get());
      assertTrue(
          session.io().releasesBySender.get() < session.io().releasesInline.get(),
          "by the sender " + session.io().releasesBySender.get() + ", inline " + session.io().releasesInline.get());
    }
  }

  @Test
  void aLatestWatcherGivesBackTheValuesItSkipped() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection reader = server.connect("reader", "vision", false, null)) {
      CountDownLatch gate = new CountDownLatch(1);
      CountDownLatch inCallback = new CountDownLatch(1);
      List<Long> got = new CopyOnWriteArrayList<>();
      reader.onChange(
          Filters.addressFilter("img").withEntry(),
          change -> {
            inCallback.countDown();
            gate.await(30, TimeUnit.SECONDS);
            got.add(change.entry(BytesValue.class).value().getValue().byteAt(0) & 0xFFL);
          },
          WatchOptions.latest());
      writer.add("img", image(MIB, 0));
      assertTrue(inCallback.await(20, TimeUnit.SECONDS));
      for (int seed = 1; seed <= 6; seed++) {
        writer.overwrite("img", image(MIB, seed));
      }
      long size = image(MIB, 0).getSerializedSize();
      // The callback holds the first; of the six after it, the newest waits: the five it replaced went back.
      RealServer.waitFor(
          () -> metrics(server).getLent() >= 7 && metrics(server).getLentBytes() == 2 * size,
          Duration.ofSeconds(20),
          "the replaced values given back while the callback waits");
      gate.countDown();
      RealServer.waitFor(() -> got.size() == 2, Duration.ofSeconds(20), "the first and the newest");
      assertEquals(List.of(0L, 6L), got);
      waitForNothingLent(server);
    }
  }

  @Test
  void aClientToldNotToUseSharedMemoryGetsIdenticalValuesAsBytesAndSaysSoOnce() throws Exception {
    List<String> said = new CopyOnWriteArrayList<>();
    Handler handler =
        new Handler() {
          @Override
          public void publish(LogRecord r) {
            if (r.getMessage().contains("is not used")) {
              said.add(r.getLevel() + " " + r.getMessage());
            }
          }

          @Override
          public void flush() {}

          @Override
          public void close() {}
        };
    Logger log = Logger.getLogger("cast.client");
    log.addHandler(handler);
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection remote = server.connect("remote", "vision", false, null)) {
      GrpcServer s = transport(remote).server("vision");
      s.shared = new SharedLink(s.endpoint, () -> RealServer.token("remote", "vision", false, 0),
          within -> { throw new AssertionError("a client told not to use it does not ask"); },
          name -> name.equals(SharedLink.ENV) ? "Off" : null);
      List<ByteString> got = new CopyOnWriteArrayList<>();
      remote.onChange(Filters.addressFilter("img").withEntry(), c -> got.add(c.entry(BytesValue.class).value().getValue()));
      remote.add("from-remote", image(MIB, 9));
      writer.add("img", image(MIB, 1));
      RealServer.waitFor(() -> got.size() == 1, Duration.ofSeconds(20), "the event");
      assertEquals(image(MIB, 1).getValue(), got.get(0));
      try (ValueView view = remote.getView("img")) {
        assertFalse(view.isShared());
        assertEquals(ByteBuffer.wrap(image(MIB, 1).getValue().toByteArray()), view.field(1));
      }
      assertEquals(image(MIB, 9), writer.get("from-remote", BytesValue.class));
      assertEquals(List.of("INFO shared memory with the server at " + server.endpoint()
          + " is not used (turned off by CAST_SHARED_MEMORY=Off): values travel as bytes"), said);
      // The remote one's write came as bytes; the writer's was staged.
      assertEquals(1, metrics(server).getStagedWrites());
    } finally {
      log.removeHandler(handler);
    }
  }

  @Test
  void aStagedWriteWhoseOutcomeIsUnknownKeepsItsRegionAndOneRefusedFreesIt() throws Exception {
    try (RealServer server = new RealServer()) {
      String token = RealServer.token("writer", "vision", false, 0);
      LaunchContract contract = new LaunchContract(server.endpoint(), "writer", "vision", token, Args.empty());
      GrpcTransport transport = new GrpcTransport(contract, e -> GrpcServer.channel(e, null), Duration.ofSeconds(2));
      try (Connection writer = new Connection(transport, who -> {})) {
        writer.add("img", image(MIB, 0));
        SharedSession session = session(writer);
        assertNotNull(session);
        // A write the server refuses: its answer is known, its region free again.
        assertThrows(ConsistencyError.class, () -> writer.overwrite("img", image(MIB, 1), 99));
        assertEquals(0, session.quarantined());
        server.pause(); // takes the request, answers nothing
        long start = System.nanoTime();
        assertThrows(DeadlineExceededError.class, () -> writer.overwrite("img", image(MIB, 2)));
        assertTrue(System.nanoTime() - start < TimeUnit.SECONDS.toNanos(10), "the call ends by its deadline");
        // It may still be applied: its region is never written again while the session lives.
        assertEquals(ShmStaging.roundUp(image(MIB, 2).getSerializedSize()), session.quarantined());
      } finally {
        server.kill();
      }
    }
  }
}
