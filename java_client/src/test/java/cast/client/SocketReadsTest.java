package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import com.google.protobuf.BytesValue;
import java.nio.ByteBuffer;
import java.nio.file.Files;
import java.nio.file.Path;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.TimeUnit;
import org.junit.jupiter.api.AfterAll;
import org.junit.jupiter.api.BeforeAll;
import org.junit.jupiter.api.Test;
import org.junit.jupiter.api.TestInstance;

/**
 * Single-entry reads on the shared-memory session's socket against a real server on this host
 * ({@link RealServer}): a Java component with a session sends its get as a {@code WriteRequest} in
 * a WRITES frame ({@link WriteStream#read}; docs/client-protocol.md, "Writes on the session's
 * socket", "Reads on the socket"), not as the unary Get. It sees the writes sent before it, the
 * pipelined ones too; a large value comes lent on a read call of the session, identical, and is
 * given back; a missing entry is NotFoundError as from the unary call; a renewed token's get goes
 * on the new session; a get the session refuses (its token expired) is made again as the unary
 * call; and a session whose server does not say it answers gets there ({@code
 * SharedMemoryInfo.reads} false: a server of an older release) gets the unary call. The twin of
 * tests/client/test_socket_reads.py.
 */
@TestInstance(TestInstance.Lifecycle.PER_CLASS)
class SocketReadsTest {
  static final int MIB = SharedMemoryTest.MIB;
  private RealServer server;

  @BeforeAll
  void startServer() throws Exception {
    server = new RealServer();
  }

  @AfterAll
  void stopServer() throws Exception {
    server.close();
  }

  static BytesValue small(String text) {
    return BytesValue.newBuilder().setValue(com.google.protobuf.ByteString.copyFromUtf8(text)).build();
  }

  @Test
  void aGetGoesOnTheSessionsSocketAfterTheWritesPipelinedBeforeIt() throws Exception {
    RealServer.Calls calls = new RealServer.Calls();
    try (Connection c = server.connect("sr-pipeliner", "vision", false, calls)) {
      c.add("sr-n", small("0"));
      SharedSession session = SharedMemoryTest.session(c);
      assertNotNull(session, "a session");
      assertTrue(session.reads, "this server answers gets on the socket (SharedMemoryInfo.reads)");
      List<CompletableFuture<WriteResult>> futures = new ArrayList<>();
      for (int i = 1; i <= 50; i++) {
        futures.add(c.overwriteAsync("sr-n", small(Integer.toString(i))));
      }
      long frames = session.writes().framesSent.get();
      assertEquals(51, frames, "the writes, each in a WRITES frame");
      // Sent after the 50 writes on the same socket, answered in order with them: it sees them all.
      assertEquals(small("50"), c.get("sr-n", BytesValue.class));
      assertEquals(frames + 1, session.writes().framesSent.get(), "the get, in a WRITES frame of its own");
      long revision = 0;
      for (CompletableFuture<WriteResult> f : futures) {
        long r = f.get(30, TimeUnit.SECONDS).revision();
        assertTrue(r > revision, "applied in call order");
        revision = r;
      }
      Entry<BytesValue> entry = c.getEntry("sr-n", BytesValue.class);
      assertEquals(revision, entry.revision(), "the entry as the last write left it");
      assertEquals("sr-pipeliner", entry.author());
      assertEquals(frames + 2, session.writes().framesSent.get());
      assertSame(session, SharedMemoryTest.session(c), "the same session throughout");
      assertEquals(0, calls.count("WorkingMemory/Get"), calls.methods.toString());
      assertEquals(0, calls.count("WorkingMemory/Write"), calls.methods.toString());
    }
  }

  @Test
  void aLargeValueReadOnTheSocketIsLentIdenticalAndGivenBackAndAMissingEntryIsNotFound() throws Exception {
    RealServer.Calls calls = new RealServer.Calls();
    BytesValue big = SharedMemoryTest.image(MIB, 3);
    try (Connection writer = server.connect("sr-writer", "vision", false, null);
        Connection reader = server.connect("sr-reader", "vision", false, calls)) {
      writer.add("sr-img", big);
      SharedSession session = SharedMemoryTest.session(reader);
      assertNotNull(session);
      long frames = session.writes().framesSent.get();
      try (ValueView view = reader.getView("sr-img")) {
        assertTrue(view.isShared(), "lent on a read call of the session, not sent as bytes");
        assertEquals(ByteBuffer.wrap(big.getValue().toByteArray()), view.field(1));
        assertEquals(big, view.decode(BytesValue.class));
        assertEquals("sr-writer", view.author());
        assertTrue(SharedMemoryTest.metrics(server).getLentBytes() >= big.getSerializedSize(), "held while viewed");
      }
      assertEquals(big, reader.get("sr-img", BytesValue.class)); // lent, decoded, given back
      NotFoundError missing = assertThrows(NotFoundError.class, () -> reader.get("sr-missing", BytesValue.class));
      assertTrue(missing.getMessage().contains("'sr-missing'"), missing.getMessage());
      assertEquals(frames + 3, session.writes().framesSent.get(), "the three gets went on the socket");
      assertEquals(0, calls.count("WorkingMemory/Get"), calls.methods.toString());
      assertSame(session, SharedMemoryTest.session(reader), "the session lives on after the refusal");
      SharedMemoryTest.waitForNothingLent(server); // RELEASE for each lease, RECEIVED for each call
      assertEquals(0, session.writes().outstanding());
    }
  }

  @Test
  void aGetAfterTheTokenWasRenewedGoesOnTheNewSession() throws Exception {
    Path file = Files.createTempFile("cast-junit-token", "");
    RealServer.Calls calls = new RealServer.Calls();
    try {
      SocketWritesTest.renew(file, RealServer.token("sr-renewed", "vision", false, 0));
      try (Connection reader =
          server.connect(
              new LaunchContract(server.endpoint(), "sr-renewed", "vision", "", Args.empty(), null, file.toString()),
              calls)) {
        reader.add("sr-t", small("1"));
        assertEquals(small("1"), reader.get("sr-t", BytesValue.class));
        SharedSession first = SharedMemoryTest.transport(reader).server("vision").shared.current();
        assertNotNull(first);
        assertEquals(2, first.writes().framesSent.get(), "the add and the get");
        Thread.sleep(1100); // a token issued later differs; the file is looked at once a second
        String renewed = RealServer.token("sr-renewed", "vision", false, 0);
        SocketWritesTest.renew(file, renewed);
        assertEquals(small("1"), reader.get("sr-t", BytesValue.class));
        SharedSession second = SharedMemoryTest.transport(reader).server("vision").shared.current();
        assertNotSame(first, second);
        assertNotNull(first.dead(), "the old session ended");
        assertEquals(renewed, second.token, "the new session's HELLO carried the renewed token");
        assertEquals(1, second.writes().framesSent.get(), "the get went on the new session");
        assertEquals(0, calls.count("WorkingMemory/Get"), calls.methods.toString());
      }
    } finally {
      Files.deleteIfExists(file);
    }
  }

  @Test
  void aGetTheSessionRefusesAsUnauthenticatedIsMadeAgainAsTheUnaryCall() throws Exception {
    long expires = System.currentTimeMillis() / 1000 + 2;
    String token = RealServer.token("sr-expiring", "vision", false, expires);
    RealServer.Calls calls = new RealServer.Calls();
    try (Connection reader =
        server.connect(new LaunchContract(server.endpoint(), "sr-expiring", "vision", token, Args.empty()), calls)) {
      reader.add("sr-e", small("e"));
      SharedSession session = SharedMemoryTest.session(reader);
      assertNotNull(session);
      RealServer.waitFor(
          () -> System.currentTimeMillis() / 1000.0 > expires + 0.3, Duration.ofSeconds(10), "the token to expire");
      long frames = session.writes().framesSent.get();
      // Refused on the socket (the session's token expired), then by the unary call, which has no
      // newer token either: its refusal is what the caller gets.
      UnauthenticatedError refused =
          assertThrows(UnauthenticatedError.class, () -> reader.get("sr-e", BytesValue.class));
      assertTrue(refused.getMessage().contains("expired"), refused.getMessage());
      assertEquals(frames + 1, session.writes().framesSent.get(), "the get went on the socket first");
      assertEquals(1, calls.count("WorkingMemory/Get"), "then as the unary call: " + calls.methods);
    }
  }

  @Test
  void aServerThatDoesNotSayItAnswersGetsOnTheSocketGetsUnaryCalls() throws Exception {
    RealServer.Calls calls = new RealServer.Calls();
    BytesValue big = SharedMemoryTest.image(MIB, 7);
    try (Connection c = server.connect("sr-older", "vision", false, calls)) {
      c.add("sr-x", big);
      SharedSession session = SharedMemoryTest.session(c);
      assertNotNull(session);
      session.reads = false; // as from a server of an earlier release: its SharedMemoryInfo has no reads
      long frames = session.writes().framesSent.get();
      try (ValueView view = c.getView("sr-x")) {
        assertTrue(view.isShared(), "lent all the same, on the unary call");
        assertEquals(ByteBuffer.wrap(big.getValue().toByteArray()), view.field(1));
      }
      assertThrows(NotFoundError.class, () -> c.get("sr-none", BytesValue.class));
      assertEquals(frames, session.writes().framesSent.get(), "no get on the socket");
      assertEquals(2, calls.count("WorkingMemory/Get"), calls.methods.toString());
      SharedMemoryTest.waitForNothingLent(server);
    }
  }

  @Test
  void aGetWhoseSessionEndsBeforeItsReplyIsMadeAgainAsTheUnaryCall() throws Exception {
    RealServer.Calls calls = new RealServer.Calls();
    try (Connection c = server.connect("sr-ended", "vision", false, calls)) {
      c.add("sr-ended-e", small("e"));
      SharedSession session = SharedMemoryTest.session(c);
      assertNotNull(session);
      assertTrue(session.reads);
      // A frame of a kind the server does not know, ahead of the get on the same socket: the server
      // ends the session without reading the get, which the get's thread, reading its own reply,
      // finds outstanding when the socket ends.
      session.sendNow(new byte[] {2, 0, 0, 0, 99, '?'});
      assertEquals(small("e"), c.get("sr-ended-e", BytesValue.class));
      assertNotNull(session.dead(), "the server ended the session");
      // Made again as the unary call; or, had the session's reader thread seen the end before the
      // get was sent (it reads after 100 ms without a waited-for write), sent on a new session.
      SharedSession now = SharedMemoryTest.session(c);
      assertTrue(
          calls.count("WorkingMemory/Get") == 1 || (now != null && now != session),
          calls.methods.toString());
    }
  }
}
