package cast.client;

import cast.v1.SharedMemoryInfo;
import cast.v1.SystemDescription;
import io.grpc.Metadata;
import io.grpc.stub.AbstractStub;
import io.grpc.stub.MetadataUtils;
import java.io.FileDescriptor;
import java.io.IOException;
import java.io.InputStream;
import java.io.OutputStream;
import java.net.SocketTimeoutException;
import java.nio.file.Files;
import java.nio.file.Path;
import java.time.Duration;
import java.util.List;
import java.util.Locale;
import java.util.Set;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.locks.ReentrantLock;
import java.util.function.Function;
import java.util.function.Supplier;
import java.util.logging.Logger;
import org.newsclub.net.unix.AFUNIXSocket;
import org.newsclub.net.unix.AFUNIXSocketAddress;
import org.newsclub.net.unix.AFUNIXSocketCredentials;

/**
 * Large values by shared memory with one server on this host: is there a session
 * (docs/client-protocol.md, "The session, step by step"). Each server the transport reaches has
 * one. On first need it asks that server where its shared memory is ({@code
 * SystemDescription.shared_memory}), connects to that Unix socket in the abstract namespace
 * (only reachable from the server's host, or network namespace) through junixsocket, checks
 * that the server runs as this process's OS user, says HELLO with the token and gets WELCOME: a
 * session id, the staging area (a memory file) and the threshold, from the server it asked
 * (its {@code server_id}). If any of that fails, values travel as bytes and the link says why
 * once at INFO; it tries again after a few seconds. {@code CAST_SHARED_MEMORY=off} in the
 * environment turns it off. Opened on a call's way, it takes at most the call's time left. The
 * twin of python/cast/client/shm.py and cpp_client/src/shm.cc; the session itself is a {@link
 * SharedSession}.
 */
final class SharedLink {
  private static final Logger LOG = Logger.getLogger("cast.client");
  /** {@code off} (or {@code 0}, {@code false}, {@code no}; any case) in the environment: never shared memory. */
  static final String ENV = "CAST_SHARED_MEMORY";
  private static final Set<String> OFF = Set.of("off", "0", "false", "no");
  static final long CONNECT_MS = 2000; // the handshake's bound
  static final long RETRY_MS = 5000; // how long after a failure the link tries again
  static final long RETRY_ELSEWHERE_MS = 60_000; // ... when the server is elsewhere or offers none
  private static final int ANCILLARY_BYTES = 1024; // room for the descriptors of 16 frames and more
  /** A renewed token: how long the old session's outstanding writes may take before it ends. */
  static final Duration RENEW_DRAIN = WriteStream.DRAIN;

  /** Why there is no session; {@code elsewhere}: the server is on another host (trying again soon is no use). */
  static final class NoSession extends Exception {
    private static final long serialVersionUID = 1L;
    final boolean elsewhere;

    NoSession(String why, boolean elsewhere) {
      super(why);
      this.elsewhere = elsewhere;
    }
  }

  final String endpoint;
  private final Supplier<String> token;
  private final Function<Duration, SystemDescription> describe;
  private final Function<String, String> environment;
  private final ReentrantLock opening = new ReentrantLock(); // held while a session is being opened
  private volatile SharedSession session;
  private volatile SharedSession retiring; // renew(): the old session, while its writes are answered
  private long retryAt; // System.nanoTime(); guarded by opening
  private boolean told; // the fallback was said at INFO; guarded by opening
  private volatile String reason = ""; // why values travel as bytes, while they do
  private volatile boolean closed;

  /**
   * Shared memory with the server at {@code endpoint}: {@code describe} asks that server (not
   * the directory) for its description within the given time (null: its own bound), {@code
   * token} is the token of the moment.
   */
  SharedLink(String endpoint, Supplier<String> token, Function<Duration, SystemDescription> describe) {
    this(endpoint, token, describe, System::getenv);
  }

  SharedLink(
      String endpoint,
      Supplier<String> token,
      Function<Duration, SystemDescription> describe,
      Function<String, String> environment) {
    this.endpoint = endpoint;
    this.token = token;
    this.describe = describe;
    this.environment = environment;
  }

  /** Whether {@code value} of {@link #ENV} turns shared memory off. */
  static boolean turnsOff(String value) {
    return value != null && OFF.contains(value.trim().toLowerCase(Locale.ROOT));
  }

  /** The live session, opened now if none is (at most every few seconds after a failure); null: bytes. */
  SharedSession session() {
    return session(null);
  }

  /**
   * The live session, as {@link #session()}, opened in at most {@code within} (a call's time
   * left, waiting for another thread's opening included; null: the opening's own bounds).
   */
  SharedSession session(Duration within) {
    SharedSession s = session;
    if (s != null && s.dead() == null) {
      return s;
    }
    long started = System.nanoTime();
    if (within == null) {
      opening.lock();
    } else {
      try {
        if (!opening.tryLock(within.toNanos(), TimeUnit.NANOSECONDS)) {
          return null; // another thread is opening it: this call goes as bytes
        }
      } catch (InterruptedException e) {
        Thread.currentThread().interrupt();
        return null;
      }
    }
    try {
      s = session;
      if (s != null && s.dead() == null) {
        return s;
      }
      if (closed || System.nanoTime() - retryAt < 0) {
        return null;
      }
      Duration left = within == null ? null : within.minusNanos(System.nanoTime() - started);
      if (left != null && (left.isNegative() || left.isZero())) {
        return null;
      }
      session = s = open(left);
      return s;
    } finally {
      opening.unlock();
    }
  }

  /**
   * {@link #session(Duration)} for a write sent with the token of the moment: a session opened
   * with an older one (the token was renewed) gives way first ({@link #renew}), so that a value is
   * staged in the session its write goes on, with the new token's identity, not in one the write's
   * renewal then ends (the server would refuse the staged value of a session that is gone).
   */
  SharedSession writerSession(Duration within) {
    SharedSession s = session(within);
    if (s != null && !s.token.equals(token.get())) {
      renew(s, RENEW_DRAIN);
      s = session(within);
    }
    return s;
  }

  /**
   * The session that gave way to a renewed token while its outstanding writes are answered, or
   * null: a write on the new session waits for them first ({@link WriteStream}), so that none
   * overtakes an earlier one.
   */
  SharedSession retiring() {
    return retiring;
  }

  /** The live session, never opened here; null without one. */
  SharedSession current() {
    SharedSession s = session;
    return s != null && s.dead() == null ? s : null;
  }

  /**
   * Its token was renewed: {@code old} (if still the link's session) gives way, once its
   * outstanding writes were answered (for at most {@code drain}), so that the next use opens a
   * new session with the token of the moment in its HELLO, and no write on the new one overtakes
   * an earlier one.
   */
  void renew(SharedSession old, Duration drain) {
    opening.lock();
    try {
      if (session != old) {
        return; // it ended, or was replaced, meanwhile
      }
      retiring = old; // before a new session can be opened: whoever writes on that one sees it
      session = null;
    } finally {
      opening.unlock();
    }
    try {
      old.writes().drain(drain);
      old.end("its token was renewed");
    } finally {
      if (retiring == old) {
        retiring = null;
      }
    }
  }

  /** A new read call of the session (its metadata), or null without one. */
  SharedSession.ReadCall newCall() {
    return newCall((Duration) null);
  }

  /** A new read call of the session opened in at most {@code within} ({@link #session(Duration)}), or null. */
  SharedSession.ReadCall newCall(Duration within) {
    SharedSession s = session(within);
    return s == null ? null : s.newCall();
  }

  /**
   * A new read call of {@code link}'s session, opened in at most {@code within}, or null (no
   * link, or no session: the values come as bytes).
   */
  static SharedSession.ReadCall newCall(SharedLink link, Duration within) {
    return link == null ? null : link.newCall(within);
  }

  static final Metadata.Key<String> METADATA_KEY =
      Metadata.Key.of(SharedSession.METADATA_KEY, Metadata.ASCII_STRING_MARSHALLER);

  /** {@code stub} naming the session and the read call {@code read} in its metadata (null: as it is). */
  static <S extends AbstractStub<S>> S lending(S stub, SharedSession.ReadCall read) {
    if (read == null) {
      return stub;
    }
    Metadata md = new Metadata();
    md.put(METADATA_KEY, read.metadata());
    return stub.withInterceptors(MetadataUtils.newAttachHeadersInterceptor(md));
  }

  /** Call metadata asking for a Watch call's event batches as EVENTS frames on the session's socket. */
  static final Metadata.Key<String> EVENTS_KEY = Metadata.Key.of("cast-watch-events", Metadata.ASCII_STRING_MARSHALLER);

  /**
   * {@code stub} for a Watch call on the read call {@code read} (null: as it is): its values lent,
   * and its event batches asked for as EVENTS frames on the session's socket
   * (docs/client-protocol.md, "A watch's events on the session's socket").
   */
  static <S extends AbstractStub<S>> S watching(S stub, SharedSession.ReadCall read) {
    if (read == null) {
      return stub;
    }
    Metadata md = new Metadata();
    md.put(METADATA_KEY, read.metadata());
    md.put(EVENTS_KEY, "socket");
    return stub.withInterceptors(MetadataUtils.newAttachHeadersInterceptor(md));
  }

  /** Why values travel as bytes, while they do ("" with a session). */
  String reason() {
    return reason;
  }

  private SharedSession open(Duration within) {
    long started = System.nanoTime();
    String env = environment.apply(ENV);
    if (turnsOff(env)) {
      fallback("turned off by " + ENV + "=" + env, Long.MAX_VALUE);
      return null;
    }
    if (!System.getProperty("os.name", "").startsWith("Linux")) {
      fallback("it needs Linux (memory files and abstract Unix sockets)", Long.MAX_VALUE);
      return null;
    }
    SharedMemoryInfo info;
    try {
      info = describe.apply(within).getSharedMemory();
    } catch (RuntimeException e) { // any failure of the question is a reason to use bytes
      fallback("the server did not say where it is: " + e.getMessage(), RETRY_MS);
      return null;
    }
    if (info.getSocket().isEmpty()) {
      fallback("the server offers none (shared_memory.enabled is false there)", RETRY_ELSEWHERE_MS);
      return null;
    }
    long handshake = CONNECT_MS;
    if (within != null) { // what the question left of the call's time
      handshake = Math.min(handshake, within.minusNanos(System.nanoTime() - started).toMillis());
      if (handshake <= 0) {
        fallback("no time was left for the handshake in the call that asked for it", RETRY_MS);
        return null;
      }
    }
    try {
      SharedSession s = connect(info, token.get(), endpoint, handshake);
      reason = "";
      LOG.fine("values of at least " + s.threshold + " bytes travel by shared memory with " + endpoint);
      return s;
    } catch (NoSession e) {
      fallback(e.getMessage(), e.elsewhere ? RETRY_ELSEWHERE_MS : RETRY_MS);
    } catch (IOException | RuntimeException | LinkageError e) {
      fallback(e.toString(), RETRY_MS);
    }
    return null;
  }

  private void fallback(String why, long retryMs) {
    reason = why;
    retryAt = retryMs == Long.MAX_VALUE ? System.nanoTime() + TimeUnit.DAYS.toNanos(365 * 100)
        : System.nanoTime() + TimeUnit.MILLISECONDS.toNanos(retryMs);
    if (!told) {
      told = true;
      LOG.info("shared memory with the server at " + endpoint + " is not used (" + why + "): values travel as bytes");
    }
  }

  /** End the session; no other is opened. */
  void close() {
    closed = true;
    SharedSession s;
    opening.lock();
    try {
      s = session;
      session = null;
    } finally {
      opening.unlock();
    }
    if (s != null) {
      s.end("closed");
    }
  }

  // ------------------------------------------------------------- connecting

  /** A session with the server whose shared memory {@code info} names, as {@code token}'s holder. */
  static SharedSession connect(SharedMemoryInfo info, String token, String endpoint) throws NoSession, IOException {
    return connect(info, token, endpoint, CONNECT_MS);
  }

  /** A session as {@link #connect(SharedMemoryInfo, String, String)}, the handshake bounded by {@code withinMs}. */
  static SharedSession connect(SharedMemoryInfo info, String token, String endpoint, long withinMs)
      throws NoSession, IOException {
    long bound = Math.max(1, Math.min(withinMs, CONNECT_MS));
    long deadline = System.nanoTime() + TimeUnit.MILLISECONDS.toNanos(bound);
    if (!AFUNIXSocket.isSupported()) {
      throw new NoSession("junixsocket cannot load its native library on this machine", false);
    }
    AFUNIXSocket socket = AFUNIXSocket.newInstance();
    SharedSession session = null;
    try {
      socket.setAncillaryReceiveBufferSize(ANCILLARY_BYTES);
      try {
        socket.connect(AFUNIXSocketAddress.inAbstractNamespace(info.getSocket()), (int) bound);
      } catch (IOException e) { // ECONNREFUSED: no such name in this network namespace
        throw new NoSession(
            "its socket is not reachable from here (" + e.getMessage() + "): another host or network namespace", true);
      }
      AFUNIXSocketCredentials peer = socket.getPeerCredentials();
      long uid = effectiveUid();
      if (peer.getUid() != uid) {
        throw new NoSession(
            "the process behind its socket (" + peer.getPid() + ") runs as OS user " + peer.getUid() + ", this one as "
                + uid,
            false);
      }
      OutputStream out = socket.getOutputStream();
      InputStream in = socket.getInputStream();
      out.write(ShmWire.hello(token));
      out.flush();
      ShmWire.Reader reader = new ShmWire.Reader();
      List<ShmWire.Frame> frames = welcome(socket, in, reader, deadline, bound);
      ShmWire.Frame first = frames.get(0);
      if (first.kind() == ShmWire.REFUSED) {
        throw new NoSession("refused: " + ShmWire.text(first.body()), false);
      }
      if (first.kind() != ShmWire.WELCOME || first.fd() == null) {
        SharedSession.closeAll(first.fd());
        throw new NoSession("the server answered HELLO with a frame of kind " + first.kind(), false);
      }
      ShmWire.Welcome welcome;
      try {
        welcome = ShmWire.parseWelcome(first.body());
      } catch (ShmWire.ProtocolError e) {
        SharedSession.closeAll(first.fd());
        throw new NoSession(e.getMessage(), false);
      }
      session = new SharedSession(socket, welcome, first.fd(), endpoint, token);
      session.reads = info.getReads();
      if (!session.serverId.equals(info.getServerId())) {
        throw new NoSession(
            "its socket belongs to another server (id " + session.serverId + ", not " + info.getServerId() + ")",
            false);
      }
      socket.setSoTimeout(0);
      session.start(frames.subList(1, frames.size()), reader, in, out);
      return session;
    } catch (NoSession | IOException | RuntimeException e) {
      if (session != null) {
        session.end(e.getMessage());
      }
      socket.close();
      throw e;
    }
  }

  /** The frames of the answer to HELLO (at least one), read by {@code deadline} ({@code bound} ms after the start). */
  private static List<ShmWire.Frame> welcome(
      AFUNIXSocket socket, InputStream in, ShmWire.Reader reader, long deadline, long bound)
      throws IOException, NoSession {
    byte[] buf = new byte[ShmWire.MAX_FRAME];
    while (true) {
      long left = TimeUnit.NANOSECONDS.toMillis(deadline - System.nanoTime());
      if (left <= 0) {
        throw new NoSession("no WELCOME within " + bound / 1000.0 + " s", false);
      }
      socket.setSoTimeout((int) left);
      int n;
      try {
        n = in.read(buf);
      } catch (SocketTimeoutException e) {
        continue;
      }
      FileDescriptor[] fds = socket.getReceivedFileDescriptors();
      if (n < 0) {
        SharedSession.closeAll(fds);
        throw new NoSession("the server closed the connection after HELLO", false);
      }
      List<ShmWire.Frame> frames;
      try {
        frames = reader.feed(buf, n, fds);
      } catch (ShmWire.ProtocolError e) {
        throw new NoSession(e.getMessage(), false);
      }
      if (!frames.isEmpty()) {
        return frames;
      }
    }
  }

  /** This process's effective OS user (/proc/self/status: real, effective, saved, file system uid). */
  static long effectiveUid() throws IOException {
    for (String line : Files.readAllLines(Path.of("/proc/self/status"))) {
      if (line.startsWith("Uid:")) {
        return Long.parseLong(line.substring(4).trim().split("\\s+")[1]);
      }
    }
    throw new IOException("/proc/self/status has no Uid line");
  }
}
