package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import com.google.protobuf.ByteString;
import com.google.protobuf.BytesValue;
import com.google.protobuf.Int64Value;
import com.google.protobuf.StringValue;
import java.io.FileDescriptor;
import java.io.RandomAccessFile;
import java.nio.ByteBuffer;
import java.nio.ByteOrder;
import java.nio.MappedByteBuffer;
import java.nio.channels.FileChannel;
import java.nio.file.Files;
import java.nio.file.Path;
import java.time.Instant;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.concurrent.CopyOnWriteArrayList;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicInteger;
import org.junit.jupiter.api.Test;

/**
 * The parts of the shared-memory client that need no server: frames, the staging area's
 * regions, leases, a view's field reader, which write outcomes are unknown.
 */
class SharedPartsTest {
  @Test
  void framesArriveWholeWhateverTheReadsAndEachTakesTheNextDescriptor() throws Exception {
    ByteBuffer segment = ByteBuffer.allocate(17).order(ByteOrder.LITTLE_ENDIAN);
    segment.putInt(13).put((byte) ShmWire.SEGMENT).putInt(7).putLong(1L << 26);
    ByteBuffer retire = ByteBuffer.allocate(9).order(ByteOrder.LITTLE_ENDIAN);
    retire.putInt(5).put((byte) ShmWire.RETIRE).putInt(7);
    byte[] both = new byte[26];
    System.arraycopy(segment.array(), 0, both, 0, 17);
    System.arraycopy(retire.array(), 0, both, 17, 9);
    FileDescriptor fd = new FileDescriptor();
    ShmWire.Reader reader = new ShmWire.Reader();
    // The descriptor comes with the first byte; the frames come in pieces.
    assertEquals(List.of(), reader.feed(both, 3, new FileDescriptor[] {fd}));
    byte[] rest = new byte[23];
    System.arraycopy(both, 3, rest, 0, 23);
    List<ShmWire.Frame> frames = reader.feed(rest, 23, null);
    assertEquals(2, frames.size());
    assertSame(fd, frames.get(0).fd());
    assertArrayEquals(new long[] {7, 1L << 26}, ShmWire.parseSegment(frames.get(0).body()));
    assertNull(frames.get(1).fd());
    assertEquals(7, ShmWire.parseRetire(frames.get(1).body()));
    // A SEGMENT without its memory file, and a length past the limit, break the protocol.
    ShmWire.ProtocolError missing =
        assertThrows(ShmWire.ProtocolError.class, () -> new ShmWire.Reader().feed(segment.array(), 17, null));
    assertTrue(missing.getMessage().contains("without its memory file"), missing.getMessage());
    byte[] huge = ByteBuffer.allocate(5).order(ByteOrder.LITTLE_ENDIAN).putInt(70_000).put((byte) 2).array();
    assertThrows(ShmWire.ProtocolError.class, () -> new ShmWire.Reader().feed(huge, 5, null));
  }

  @Test
  void theReaderSaysHowManyBytesOfTheFrameBegunAreStillToCome() throws Exception {
    // What sizes the session's next read (SessionSocket.readLength): junixsocket copies as many bytes as a read asks.
    ShmWire.Reader reader = new ShmWire.Reader();
    assertEquals(0, reader.wanted(), "nothing begun");
    ByteBuffer events = ByteBuffer.allocate(4 + 1 + 100_000).order(ByteOrder.LITTLE_ENDIAN);
    events.putInt(1 + 100_000).put((byte) ShmWire.EVENTS);
    byte[] frame = events.array();
    reader.feed(frame, 2, null);
    assertEquals(2, reader.wanted(), "the rest of the length prefix");
    reader.feed(java.util.Arrays.copyOfRange(frame, 2, 5), 3, null);
    assertEquals(100_000, reader.wanted());
    reader.feed(java.util.Arrays.copyOfRange(frame, 5, 60_005), 60_000, null);
    assertEquals(40_000, reader.wanted());
    List<ShmWire.Frame> done = reader.feed(java.util.Arrays.copyOfRange(frame, 60_005, frame.length), 40_000, null);
    assertEquals(1, done.size());
    assertEquals(100_000, done.get(0).body().remaining());
    assertEquals(0, reader.wanted(), "the frame ended where the read did");
  }

  @Test
  void clientFramesAreLittleEndianAndReleasesAreGathered() {
    ByteBuffer hello = ByteBuffer.wrap(ShmWire.hello("tok")).order(ByteOrder.LITTLE_ENDIAN);
    assertEquals(6, hello.getInt());
    assertEquals(ShmWire.HELLO, hello.get());
    assertEquals(ShmWire.HELLO_VERSION, hello.getShort());
    assertArrayEquals(new byte[] {1, 0, 0, 0, (byte) ShmWire.NUDGE}, ShmWire.nudge());
    ByteBuffer received = ByteBuffer.wrap(ShmWire.received(3, 64, true)).order(ByteOrder.LITTLE_ENDIAN);
    assertEquals(18, received.getInt());
    assertEquals(ShmWire.RECEIVED, received.get());
    assertEquals(3, received.getLong());
    assertEquals(64, received.getLong());
    assertEquals(1, received.get());
    List<Long> ids = new java.util.ArrayList<>();
    for (long i = 0; i < ShmWire.RELEASE_IDS + 1; i++) {
      ids.add(i);
    }
    List<byte[]> releases = ShmWire.release(ids);
    assertEquals(2, releases.size()); // one frame holds RELEASE_IDS ids (within the 64 KiB limit)
    assertEquals(5 + 8 * ShmWire.RELEASE_IDS, releases.get(0).length);
    assertTrue(releases.get(0).length - 4 <= ShmWire.MAX_FRAME);
    ByteBuffer last = ByteBuffer.wrap(releases.get(1)).order(ByteOrder.LITTLE_ENDIAN);
    assertEquals(9, last.getInt());
    last.get();
    assertEquals(ShmWire.RELEASE_IDS, last.getLong());
  }

  @Test
  void stagingRegionsAreWholePagesFreedWhenTheOutcomeIsKnownAndKeptWhenNot() throws Exception {
    Path file = Files.createTempFile("staging", ".bin");
    try (RandomAccessFile raf = new RandomAccessFile(file.toFile(), "rw")) {
      raf.setLength(4 * ShmStaging.PAGE);
      MappedByteBuffer map = raf.getChannel().map(FileChannel.MapMode.READ_WRITE, 0, 4 * ShmStaging.PAGE);
      ShmStaging staging = new ShmStaging(map);
      ShmStaging.Staged a = staging.stage(ByteString.copyFrom(new byte[5000])); // two pages
      ShmStaging.Staged b = staging.stage(ByteString.copyFromUtf8("b"));
      assertEquals(0, a.offset());
      assertEquals(2 * ShmStaging.PAGE, a.taken());
      assertEquals(2 * ShmStaging.PAGE, b.offset());
      assertEquals((byte) 'b', map.get(2 * ShmStaging.PAGE));
      assertNull(staging.stage(ByteString.copyFrom(new byte[2 * ShmStaging.PAGE]))); // no room: bytes
      staging.unstage(a, true);
      staging.unstage(b, false); // unknown outcome: never written again
      assertEquals(ShmStaging.PAGE, staging.quarantined());
      assertEquals(3 * ShmStaging.PAGE, staging.freeBytes());
      ShmStaging.Staged c = staging.stage(ByteString.copyFrom(new byte[2 * ShmStaging.PAGE]));
      assertEquals(0, c.offset());
      staging.close();
      assertNull(staging.stage(ByteString.copyFromUtf8("after the end")));
    } finally {
      Files.delete(file);
    }
  }

  @Test
  void aLeaseIsGivenBackOnceByItsLastHolderAndNeverRetainedAfter() {
    AtomicInteger given = new AtomicInteger();
    Lease lease = new Lease(ByteBuffer.wrap(new byte[] {1, 2, 3}), given::incrementAndGet);
    assertTrue(lease.retain());
    lease.release();
    assertEquals(0, given.get());
    lease.release();
    assertEquals(1, given.get());
    assertFalse(lease.retain());
    lease.release(); // one too many: nothing
    assertEquals(1, given.get());
    assertFalse(lease.isHeld());
  }

  @Test
  void aLeaseNobodyReleasedIsGivenBackWhenItIsGarbage() throws Exception {
    AtomicInteger given = new AtomicInteger();
    new Lease(ByteBuffer.allocate(8), given::incrementAndGet); // a view never closed
    for (int i = 0; i < 200 && given.get() == 0; i++) {
      System.gc();
      Thread.sleep(10);
    }
    assertEquals(1, given.get());
  }

  private static Transport.StoredEntry stored(com.google.protobuf.Message value, Lease lease) {
    return new Transport.StoredEntry(
        new WorkingMemoryAddress("img", "vision"),
        value.getDescriptorForType().getFullName(),
        value.toByteString(),
        4,
        "writer",
        9,
        Instant.EPOCH,
        lease);
  }

  @Test
  void aViewReadsFieldsInPlaceAndRefusesWhatIsNoMessage() {
    BytesValue image = BytesValue.newBuilder().setValue(ByteString.copyFromUtf8("pixels")).build();
    AtomicInteger given = new AtomicInteger();
    Lease lease = new Lease(image.toByteString().asReadOnlyByteBuffer(), given::incrementAndGet);
    ValueView view = new ValueView(stored(image, lease));
    assertTrue(view.isShared());
    assertEquals(ByteBuffer.wrap("pixels".getBytes()), view.field(1));
    assertEquals(0, view.field(2).remaining()); // absent
    assertEquals(image, view.decode(BytesValue.class));
    assertThrows(InvalidArgumentError.class, () -> view.decode(StringValue.class));
    view.close();
    assertEquals(1, given.get());
    assertThrows(InvalidArgumentError.class, view::data);
    view.close(); // idempotent
    assertEquals(1, given.get());

    ValueView number = new ValueView(stored(Int64Value.of(7), null));
    assertFalse(number.isShared());
    InvalidArgumentError notBytes = assertThrows(InvalidArgumentError.class, () -> number.field(1));
    assertTrue(notBytes.getMessage().contains("field 1 is a number"), notBytes.getMessage());
    // The last occurrence wins, as when protobuf parses; a length past the end is no message.
    ByteBuffer twice = ByteBuffer.wrap(new byte[] {10, 1, 'a', 10, 2, 'b', 'c'});
    assertEquals(ByteBuffer.wrap(new byte[] {'b', 'c'}), ValueView.fieldOf(twice, 1, "v"));
    assertThrows(InvalidArgumentError.class, () -> ValueView.fieldOf(ByteBuffer.wrap(new byte[] {10, 9, 'a'}), 1, "v"));
    assertThrows(InvalidArgumentError.class, () -> ValueView.fieldOf(ByteBuffer.wrap(new byte[] {(byte) 0x80}), 1, "v"));
  }

  private static Transport.Change lentChange(BytesValue image, AtomicInteger given) {
    Lease lease = new Lease(image.toByteString().asReadOnlyByteBuffer(), given::incrementAndGet);
    return new Transport.Change(
        9, Operation.OVERWRITE, new WorkingMemoryAddress("img", "vision"), "google.protobuf.BytesValue", 4, "w",
        "vision", Instant.EPOCH, stored(image, lease), List.of(1));
  }

  @Test
  void aChangeCopiesItsLentValueOnceUnlessItsCallbackTookAView() {
    BytesValue image = BytesValue.newBuilder().setValue(ByteString.copyFromUtf8("x")).build();
    // Read in the callback: copied then (once), readable later, the lease given back at the end.
    AtomicInteger given = new AtomicInteger();
    Transport.Change read = lentChange(image, given);
    WorkingMemoryChange c = new WorkingMemoryChange(read);
    assertEquals(image, c.entry(BytesValue.class).value());
    c.callbackReturned();
    read.entry().release(); // the dispatcher's hold
    assertEquals(1, given.get());
    assertEquals(image, c.entry(BytesValue.class).value());
    // Not read in the callback: copied when it returns.
    AtomicInteger given2 = new AtomicInteger();
    Transport.Change unread = lentChange(image, given2);
    WorkingMemoryChange stored = new WorkingMemoryChange(unread);
    stored.callbackReturned();
    unread.entry().release();
    assertEquals(1, given2.get());
    assertEquals(image, stored.entry(BytesValue.class).value());
    try (ValueView late = stored.view()) {
      assertFalse(late.isShared()); // the copy
      assertEquals(image, late.decode(BytesValue.class));
    }
    // A view taken in the callback: no copy; the view holds the value, the change cannot read it later.
    AtomicInteger given3 = new AtomicInteger();
    Transport.Change viewed = lentChange(image, given3);
    WorkingMemoryChange v = new WorkingMemoryChange(viewed);
    ValueView view = v.view();
    assertTrue(view.isShared());
    v.callbackReturned();
    viewed.entry().release();
    assertEquals(0, given3.get()); // the view holds it
    assertEquals(image, view.decode(BytesValue.class));
    view.close();
    assertEquals(1, given3.get());
    InvalidArgumentError late = assertThrows(InvalidArgumentError.class, () -> v.entry(BytesValue.class));
    assertTrue(late.getMessage().contains("read it through that view"), late.getMessage());
    assertThrows(InvalidArgumentError.class, v::view);
  }

  private static Transport.Change lent(long revision, int watchId, AtomicInteger given) {
    BytesValue image = BytesValue.newBuilder().setValue(ByteString.copyFromUtf8("x")).build();
    Lease lease = new Lease(image.toByteString().asReadOnlyByteBuffer(), given::incrementAndGet);
    return new Transport.Change(revision, Operation.OVERWRITE, new WorkingMemoryAddress("img", "vision"),
        "google.protobuf.BytesValue", revision, "w", "vision", Instant.EPOCH, stored(image, lease), List.of(watchId));
  }

  @Test
  void theDispatcherGivesBackALentValueWhenItsCallbackRanOrANewerOneReplacedIt() throws Exception {
    Dispatcher d = new Dispatcher("lent", 100, DispatcherTest.LOG);
    FakeTransport t = new FakeTransport(new FakeTransport.Memory("vision"), new Identity("c", "vision", false));
    CountDownLatch inCallback = new CountDownLatch(1);
    CountDownLatch gate = new CountDownLatch(1);
    List<Long> seen = new CopyOnWriteArrayList<>();
    ChangeFilter filter = Filters.addressFilter(new WorkingMemoryAddress("img", "vision")).withEntry();
    ChangeCallback slow =
        c -> {
          inCallback.countDown();
          gate.await(10, TimeUnit.SECONDS);
          seen.add(c.revision());
        };
    int latest = d.watch(t, List.of(filter), slow, WatchOptions.latest()).watchId();
    List<AtomicInteger> given = new ArrayList<>();
    List<Transport.Change> changes = new ArrayList<>(); // held here: no lease becomes garbage meanwhile
    for (int rev = 1; rev <= 6; rev++) {
      given.add(new AtomicInteger());
      changes.add(lent(rev, latest, given.get(rev - 1)));
      d.deliver(changes.get(rev - 1));
      if (rev == 1) {
        assertTrue(inCallback.await(10, TimeUnit.SECONDS));
      }
    }
    // The first is in the callback; of the five after it the newest waits: the four it replaced went back.
    assertEquals(List.of(0, 1, 1, 1, 1, 0), given.stream().map(AtomicInteger::get).toList());
    gate.countDown();
    assertTrue(d.drain(Duration.ofSeconds(10)));
    assertEquals(List.of(1L, 6L), seen);
    assertEquals(List.of(1, 1, 1, 1, 1, 1), given.stream().map(AtomicInteger::get).toList()); // each once
    // A queue watch's callback: given back once it ran.
    int queue = d.watch(t, List.of(filter), c -> seen.add(c.revision()), WatchOptions.queue()).watchId();
    AtomicInteger last = new AtomicInteger();
    Transport.Change change = lent(7, queue, last);
    d.deliver(change);
    assertTrue(d.drain(Duration.ofSeconds(10)));
    assertEquals(7L, seen.get(2));
    assertEquals(1, last.get());
    d.stop(Duration.ofSeconds(1));
  }

  @Test
  void onlyWritesThatMayStillBeAppliedKeepTheirRegions() {
    assertTrue(StagedWrite.inDoubt(new UnavailableError("broke")));
    assertTrue(StagedWrite.inDoubt(new DeadlineExceededError("no reply")));
    assertTrue(StagedWrite.inDoubt(new CastError("CANCELLED", "interrupted")));
    assertTrue(StagedWrite.inDoubt(new IllegalStateException("not an answer")));
    assertFalse(StagedWrite.inDoubt(new ConsistencyError("version")));
    assertFalse(StagedWrite.inDoubt(new InvalidArgumentError("refused")));
    assertFalse(StagedWrite.inDoubt(new PermissionDeniedError("refused")));
  }

  @Test
  void theEnvironmentTurnsItOff() {
    for (String off : List.of("off", "0", "false", "NO", " Off ")) {
      assertTrue(SharedLink.turnsOff(off), off);
    }
    for (String on : List.of("on", "", "1", "yes")) {
      assertFalse(SharedLink.turnsOff(on), on);
    }
    assertFalse(SharedLink.turnsOff(null));
  }
}
