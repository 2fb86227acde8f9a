package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.testing.CastTesting.Frame;
import cast.testing.CastTesting.Pose;
import cast.v1.StagedValue;
import com.google.protobuf.ByteString;
import java.io.IOException;
import java.nio.ByteBuffer;
import java.nio.file.Files;
import java.nio.file.Path;
import java.time.Duration;
import java.util.HashSet;
import java.util.List;
import java.util.Set;
import java.util.concurrent.CopyOnWriteArrayList;
import java.util.concurrent.TimeUnit;
import org.junit.jupiter.api.Test;
import org.junit.jupiter.api.function.Executable;

/**
 * Loans: a large value written in place (docs/java.md, "Writing a large value in place (loans)"),
 * between the Java client and a real server on this host as {@link SharedMemoryTest} runs it
 * ({@link RealServer}: {@code cast serve}, shared memory on). The library's internals (the
 * session, its staging area, a loan's region) are reached from this package to check that
 * nothing is copied where nothing should be.
 */
class LoanTest {
  static final int MIB = 1 << 20;

  /** A frame with every field set but its pixels (and its repeated parts). */
  static Frame frame() {
    return Frame.newBuilder().setWidth(1024).setHeight(1024).setEncoding("mono8").build();
  }

  static byte[] pixels(int size, int seed) {
    byte[] b = new byte[size];
    for (int i = 0; i < size; i++) {
      b[i] = (byte) ((seed + i * 7) % 251);
    }
    return b;
  }

  /** {@code buffer} filled with {@link #pixels}, in place, from its position 0. */
  static void fill(ByteBuffer buffer, int seed) {
    buffer.put(0, pixels(buffer.limit(), seed));
  }

  /** The frame a loan filled with {@link #pixels} of {@code seed} holds. */
  static Frame filled(int size, int seed) {
    return frame().toBuilder().setPixels(ByteString.copyFrom(pixels(size, seed))).build();
  }

  static SharedSession session(Connection c) {
    return SharedMemoryTest.session(c);
  }

  @Test
  void aLoanedFrameIsWrittenInPlaceAndReadBackIdenticalByEveryReader() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null);
        Connection reader = server.connect("reader", "vision", false, null)) {
      List<String> seen = new CopyOnWriteArrayList<>();
      reader.onChange(
          Filters.addressFilter("camera").withEntry(),
          change -> {
            int seed = seen.size() + 1; // the add's pixels, then the overwrite's
            try (ValueView view = change.view()) {
              boolean right = view.decode(Frame.class).equals(filled(MIB, seed))
                  && view.field(4).equals(ByteBuffer.wrap(pixels(MIB, seed)));
              seen.add(change.operation() + " shared=" + view.isShared() + " right=" + right);
            }
          });
      long staged = SharedMemoryTest.metrics(server).getStagedWrites();
      WriteResult added;
      try (Loan loan = writer.loan(frame(), "pixels", MIB)) {
        assertTrue(loan.shared());
        assertEquals(MIB, loan.size());
        ByteBuffer buffer = loan.buffer();
        assertFalse(buffer.isReadOnly());
        assertEquals(0, buffer.position());
        assertEquals(MIB, buffer.limit());
        assertEquals(0, buffer.alignmentOffset(0, 64), "the pixels start on a cache line");
        fill(buffer, 1);
        added = writer.add("camera", loan);
      }
      assertEquals(filled(MIB, 1), reader.get("camera", Frame.class));
      try (Loan loan = writer.loan(frame(), "pixels", MIB)) {
        assertTrue(loan.shared());
        fill(loan.buffer(), 2);
        assertTrue(writer.overwrite("camera", loan).version() > added.version());
      }
      RealServer.waitFor(() -> seen.size() == 2, Duration.ofSeconds(20), "two events");
      assertEquals(List.of("ADD shared=true right=true", "OVERWRITE shared=true right=true"), seen);
      assertEquals(filled(MIB, 2), reader.get("camera", Frame.class));
      assertEquals(filled(MIB, 2), writer.get("camera", Frame.class));
      try (ValueView view = reader.getView("camera")) {
        assertTrue(view.isShared());
        assertEquals(ByteBuffer.wrap(pixels(MIB, 2)), view.field(4));
      }
      assertEquals(staged + 2, SharedMemoryTest.metrics(server).getStagedWrites()); // both by the loans' places
      SharedMemoryTest.waitForNothingLent(server);
    }
  }

  @Test
  void aLoansBufferIsTheStagingAreaAndItsWriteCarriesNoValueBytes() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null)) {
      Loan loan = writer.loan(frame(), "pixels", MIB);
      SharedSession session = session(writer);
      LoanMemory.InStaging memory = assertInstanceOf(LoanMemory.InStaging.class, loan.memory());
      assertSame(session, memory.session);
      ShmStaging.Lent lent = memory.lent;
      // The value at its place in the staging area: a header (pad before it), then the payload on a cache line.
      assertEquals(0, (lent.offset() + lent.size() - MIB) % 64);
      assertTrue(lent.offset() - lent.region().offset() < 64);
      fill(loan.buffer(), 3);
      // The buffer is the staging area's memory: what was written through it is there, a serialised Frame.
      assertEquals(filled(MIB, 3), Frame.parseFrom(session.staging().bytes(lent.offset(), lent.size())));
      loan.buffer().put(MIB - 1, (byte) 0x5A);
      assertEquals(0x5A, session.staging().bytes(lent.offset(), lent.size()).get((int) lent.size() - 1));
      fill(loan.buffer(), 3);

      long staged = SharedMemoryTest.metrics(server).getStagedWrites();
      long bytes = session.writes().bytesSent.get();
      long copies = session.staging().copiedIn.get();
      writer.add("camera", loan);
      long sent = session.writes().bytesSent.get() - bytes;
      assertTrue(sent > 0 && sent < 512, "the request carried " + sent + " bytes on the session's socket");
      assertEquals(copies, session.staging().copiedIn.get(), "nothing was copied into the staging area");
      assertEquals(staged + 1, SharedMemoryTest.metrics(server).getStagedWrites());
      assertEquals(filled(MIB, 3), writer.get("camera", Frame.class));
      // Its region was the write's, freed at the reply.
      assertEquals(session.staging().size(), session.staging().freeBytes());
      assertEquals(0, session.staging().loans());

      // What the write request says, step by step as GrpcTransport.overwrite makes it: the loan's place, no bytes.
      Loan second = writer.loan(frame(), "pixels", MIB);
      fill(second.buffer(), 4);
      ShmStaging.Lent place = ((LoanMemory.InStaging) second.memory()).lent;
      GrpcTransport transport = SharedMemoryTest.transport(writer);
      Budget budget = new Budget(Duration.ofSeconds(20));
      StagedWrite write = StagedWrite.to(transport.server("vision"), budget.left());
      second.spendFor("vision");
      StagedWrite.Value value = write.stage(second);
      assertTrue(value.value().getValue().isEmpty());
      assertEquals(Types.TYPE_URL_PREFIX + "cast.testing.Frame", value.value().getTypeUrl());
      StagedValue expected =
          StagedValue.newBuilder()
              .setSession(ByteString.copyFrom(session.id))
              .setOffset(place.offset())
              .setSize(place.size())
              .build();
      assertEquals(expected, value.staged());
      var request = Conversions.writeOverwrite("vision", "camera", value.value(), null, value.staged());
      write.call(transport.writes("vision"), request, budget);
      assertEquals(filled(MIB, 4), writer.get("camera", Frame.class));
      assertEquals(staged + 2, SharedMemoryTest.metrics(server).getStagedWrites());
    }
  }

  @Test
  void withSharedMemoryOffALoanIsPrivateMemoryAndReadersGetTheSameValue() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null, false);
        Connection reader = server.connect("reader", "vision", false, null)) {
      List<Frame> got = new CopyOnWriteArrayList<>();
      reader.onChange(
          Filters.addressFilter("camera").withEntry(), change -> got.add(change.entry(Frame.class).value()));
      try (Loan loan = writer.loan(frame(), "pixels", MIB)) {
        assertFalse(loan.shared());
        assertEquals(MIB, loan.size());
        ByteBuffer buffer = loan.buffer();
        assertFalse(buffer.isReadOnly());
        assertEquals(MIB, buffer.remaining());
        fill(buffer, 5);
        writer.add("camera", loan);
      }
      RealServer.waitFor(() -> got.size() == 1, Duration.ofSeconds(20), "the event");
      assertEquals(filled(MIB, 5), got.get(0));
      assertEquals(filled(MIB, 5), reader.get("camera", Frame.class));
      try (ValueView view = reader.getView("camera")) {
        assertTrue(view.isShared()); // the server lends it to a reader on its host all the same
        assertEquals(ByteBuffer.wrap(pixels(MIB, 5)), view.field(4));
      }
      assertEquals(0, SharedMemoryTest.metrics(server).getStagedWrites()); // its bytes came in the request
    }
  }

  @Test
  void aSmallLoanIsPrivateMemoryAndItsValueRight() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null)) {
      assertNotNull(session(writer));
      try (Loan loan = writer.loan(frame(), "pixels", 1000)) {
        assertFalse(loan.shared()); // under the threshold (64 KiB)
        fill(loan.buffer(), 6);
        writer.add("small", loan);
      }
      assertEquals(filled(1000, 6), writer.get("small", Frame.class));
      try (Loan empty = writer.loan(frame(), "pixels", 0)) {
        assertEquals(0, empty.buffer().remaining());
        writer.overwrite("small", empty);
      }
      assertEquals(frame(), writer.get("small", Frame.class));
      assertEquals(0, SharedMemoryTest.metrics(server).getStagedWrites());
    }
  }

  @Test
  void aTransportWithoutSharedMemoryWritesALoansBytes() throws Exception {
    FakeTransport.Memory memory = new FakeTransport.Memory("vision", "motor");
    try (Connection writer = new Connection(new FakeTransport(memory, new Identity("w", "vision", false)), who -> {})) {
      try (Loan loan = writer.loan(frame(), "pixels", MIB)) {
        assertFalse(loan.shared());
        fill(loan.buffer(), 11);
        writer.overwriteAsync("camera", loan).exceptionally(e -> null).get(10, TimeUnit.SECONDS); // not found
        refused("this loan was already written (or closed): take a new loan for each write",
            () -> writer.add("camera", loan));
      }
      try (Loan loan = writer.loan(frame(), "pixels", MIB)) {
        fill(loan.buffer(), 12);
        writer.add("camera", loan);
      }
      assertEquals(filled(MIB, 12), writer.get("camera", Frame.class));
      assertTrue(memory.calls.contains("Loan vision " + MIB), memory.calls.toString());
      assertEquals(1, memory.schemaRequests.size()); // the type registered once, by the first loan
    }
  }

  /** {@code call} refused with InvalidArgumentError saying {@code message} exactly. */
  static void refused(String message, Executable call) {
    InvalidArgumentError e = assertThrows(InvalidArgumentError.class, call);
    assertEquals(message, e.getMessage());
  }

  @Test
  void everyBadLoanAndBadWriteOfOneIsRefusedAndChangesNothing() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", true, null)) {
      SharedSession session = session(writer);
      long area = session.staging().size();
      Frame f = frame();
      refused(
          "Frame has no field 'pixel': a loan is taken of one of its top-level bytes fields (pixels)",
          () -> writer.loan(f, "pixel", MIB));
      refused(
          "field 'tags' of cast.testing.Pose is a repeated string: a loan is taken of a top-level singular bytes"
              + " field",
          () -> writer.loan(Pose.newBuilder().setX(1).build(), "tags", MIB));
      refused(
          "Pose has no field 'data': a loan is taken of one of its top-level bytes fields (it has none)",
          () -> writer.loan(Pose.getDefaultInstance(), "data", MIB));
      refused(
          "field 'parts' of cast.testing.Frame is a repeated bytes: a loan is taken of a top-level singular bytes"
              + " field",
          () -> writer.loan(f, "parts", MIB));
      refused(
          "field 'width' of cast.testing.Frame is a uint32: a loan is taken of a top-level singular bytes field",
          () -> writer.loan(f, "width", MIB));
      refused(
          "field 'pixels' of cast.testing.Frame already holds 3 bytes: leave it empty, the loan's buffer is its"
              + " bytes",
          () -> writer.loan(f.toBuilder().setPixels(ByteString.copyFromUtf8("abc")).build(), "pixels", MIB));
      refused("a loan's size is a number of bytes, 0 or more, not -1", () -> writer.loan(f, "pixels", -1));
      refused("entry values are protobuf messages, got null", () -> writer.loan(null, "pixels", MIB));
      // Nothing reserved, nothing registered or written.
      assertEquals(area, session.staging().freeBytes());
      assertEquals(0, session.staging().loans());
      assertFalse(writer.exists("camera"));

      // A loan written to another SA than the one it was taken for: refused, the loan untouched.
      Loan forMotor = writer.loan(f, "pixels", MIB, "motor");
      assertTrue(forMotor.shared());
      fill(forMotor.buffer(), 7);
      refused(
          "the loan was taken for subarchitecture 'motor' and is written to 'vision': take it with subarchitecture"
              + " 'vision'",
          () -> writer.add("camera", forMotor));
      refused(
          "the loan was taken for subarchitecture 'motor' and is written to 'vision': take it with subarchitecture"
              + " 'vision'",
          () -> writer.overwriteAsync("camera", forMotor, "vision"));
      assertFalse(writer.exists("camera"));
      assertEquals(1, session.staging().loans());
      writer.add("camera", forMotor, "motor"); // still whole: written where it was taken for
      assertEquals(filled(MIB, 7), writer.get("camera", Frame.class, "motor"));
      assertFalse(writer.exists("camera"));

      // A written or closed loan written again.
      Entry<Frame> before = writer.getEntry("camera", Frame.class, "motor");
      refused(
          "this loan was already written (or closed): take a new loan for each write",
          () -> writer.overwrite("camera", forMotor, "motor"));
      Loan closed = writer.loan(f, "pixels", MIB);
      closed.close();
      closed.close(); // nothing more
      refused(
          "this loan was already written (or closed): take a new loan for each write",
          () -> writer.add("camera", closed));
      refused("this loan was written (or closed): its buffer is gone; take a new loan", closed::buffer);
      assertFalse(writer.exists("camera"));
      assertEquals(before, writer.getEntry("camera", Frame.class, "motor"));
      assertEquals(area, session.staging().freeBytes());
      assertEquals(0, session.staging().loans());
    }
  }

  @Test
  void aClosedUnwrittenLoanGivesItsWholeRegionBack() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null)) {
      SharedSession session = session(writer);
      long area = session.staging().size(); // 2 x limits.max_value_bytes, rounded up
      int half = (int) (area / 2); // with its header, more than half of the area
      Loan first = writer.loan(frame(), "pixels", half);
      assertTrue(first.shared());
      try (Loan second = writer.loan(frame(), "pixels", half)) {
        assertFalse(second.shared()); // no room while the first holds its region
      }
      first.close();
      assertEquals(area, session.staging().freeBytes(), "the region, its pad included, is free again");
      try (Loan third = writer.loan(frame(), "pixels", half)) {
        assertTrue(third.shared());
        first.close(); // a closed loan's close does nothing
        assertEquals(1, session.staging().loans());
      }
      assertEquals(area, session.staging().freeBytes());
      assertEquals(0, session.staging().loans());
    }
  }

  @Test
  void aLoanIsWrittenOnceTheSecondWriteIsRefused() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null)) {
      try (Loan loan = writer.loan(frame(), "pixels", MIB)) {
        ByteBuffer buffer = loan.buffer();
        fill(buffer, 8);
        WriteResult written = writer.add("camera", loan);
        refused(
            "this loan was already written (or closed): take a new loan for each write",
            () -> writer.overwrite("camera", loan));
        refused(
            "this loan was already written (or closed): take a new loan for each write",
            () -> writer.overwriteAsync("camera", loan, written.version()));
        refused("this loan was written (or closed): its buffer is gone; take a new loan", loan::buffer);
        assertTrue(loan.shared());
        assertEquals(MIB, loan.size());
        assertEquals(written.version(), writer.getEntry("camera", Frame.class).version());
      }
      assertEquals(filled(MIB, 8), writer.get("camera", Frame.class));
    }
  }

  @Test
  void anAsyncOverwriteWithALoanWritesItAndSpendsIt() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null)) {
      WriteResult added = writer.add("camera", filled(MIB, 0));
      long staged = SharedMemoryTest.metrics(server).getStagedWrites();
      Loan loan = writer.loan(frame(), "pixels", MIB);
      assertTrue(loan.shared());
      fill(loan.buffer(), 9);
      var future = writer.overwriteAsync("camera", loan, added.version());
      refused(
          "this loan was already written (or closed): take a new loan for each write",
          () -> writer.overwriteAsync("camera", loan));
      assertEquals(added.version() + 1, future.get(30, TimeUnit.SECONDS).version());
      assertEquals(filled(MIB, 9), writer.get("camera", Frame.class));
      assertEquals(staged + 1, SharedMemoryTest.metrics(server).getStagedWrites());
      loan.close(); // written: nothing to give back
      SharedSession session = session(writer);
      assertEquals(session.staging().size(), session.staging().freeBytes());
      // An async add too, and a refusal arriving on the future spends the loan all the same.
      Loan again = writer.loan(frame(), "pixels", MIB);
      var refusedAdd = writer.addAsync("camera", again);
      Exception e = assertThrows(Exception.class, () -> refusedAdd.get(30, TimeUnit.SECONDS));
      assertInstanceOf(AlreadyExistsError.class, e.getCause());
      refused("this loan was written (or closed): its buffer is gone; take a new loan", again::buffer);
      assertEquals(session.staging().size(), session.staging().freeBytes(), "a known refusal frees the region");
    }
  }

  /** The address ranges of the staging areas this process maps (/proc/self/maps). */
  static Set<String> stagingMaps() throws IOException {
    Set<String> out = new HashSet<>();
    for (String line : Files.readAllLines(Path.of("/proc/self/maps"))) {
      if (line.contains("memfd:cast-staging")) {
        out.add(line.split(" ")[0]);
      }
    }
    return out;
  }

  @Test
  void aLoanOutlivingItsSessionKeepsItsMemoryAndIsWrittenAsBytes() throws Exception {
    try (RealServer server = new RealServer();
        Connection writer = server.connect("writer", "vision", false, null)) {
      Set<String> others = stagingMaps();
      Loan loan = writer.loan(frame(), "pixels", MIB);
      assertTrue(loan.shared());
      Set<String> areas = stagingMaps();
      areas.removeAll(others);
      assertEquals(1, areas.size(), "the writer's staging area");
      SharedSession old = session(writer);
      old.end("ended by the test");
      // The session ended with the loan open: its staging area stays mapped, its buffer usable.
      assertTrue(stagingMaps().containsAll(areas));
      fill(loan.buffer(), 10);
      long staged = SharedMemoryTest.metrics(server).getStagedWrites();
      writer.add("camera", loan); // in a new session: the bytes, copied out of the old one, staged there
      assertNotSame(old, session(writer));
      assertEquals(filled(MIB, 10), writer.get("camera", Frame.class));
      assertEquals(staged + 1, SharedMemoryTest.metrics(server).getStagedWrites());
      // The last loan in it was written: the old area is unmapped now.
      Set<String> now = stagingMaps();
      now.retainAll(areas);
      assertEquals(Set.of(), now);
    }
  }

  @Test
  void aLoanWrittenWithAnUnknownOutcomeKeepsItsRegionAndOneRefusedFreesIt() throws Exception {
    try (RealServer server = new RealServer()) {
      String token = RealServer.token("writer", "vision", false, 0);
      LaunchContract contract = new LaunchContract(server.endpoint(), "writer", "vision", token, Args.empty());
      GrpcTransport transport = new GrpcTransport(contract, e -> GrpcServer.channel(e, null), Duration.ofSeconds(2));
      try (Connection writer = new Connection(transport, who -> {})) {
        writer.add("camera", filled(MIB, 0));
        SharedSession session = session(writer);
        Loan refusedLoan = writer.loan(frame(), "pixels", MIB);
        assertThrows(ConsistencyError.class, () -> writer.overwrite("camera", refusedLoan, 99));
        assertEquals(0, session.quarantined());
        assertEquals(session.staging().size(), session.staging().freeBytes());
        Loan loan = writer.loan(frame(), "pixels", MIB);
        assertTrue(loan.shared());
        long taken = ((LoanMemory.InStaging) loan.memory()).lent.region().taken();
        server.pause(); // takes the request, answers nothing
        long start = System.nanoTime();
        assertThrows(DeadlineExceededError.class, () -> writer.overwrite("camera", loan));
        assertTrue(System.nanoTime() - start < TimeUnit.SECONDS.toNanos(10), "the call ends by its deadline");
        // It may still be applied: its region, pad and all, is never written again while the session lives.
        assertEquals(taken, session.quarantined());
        assertTrue(taken >= ShmStaging.roundUp(MIB));
      } finally {
        server.kill();
      }
    }
  }
}
