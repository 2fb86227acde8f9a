package cast.client;

import cast.v1.SharedValue;
import cast.v1.StagedValue;
import com.google.protobuf.ByteString;
import java.io.FileDescriptor;
import java.io.FileInputStream;
import java.io.IOException;
import java.io.InputStream;
import java.io.OutputStream;
import java.io.RandomAccessFile;
import java.nio.ByteBuffer;
import java.nio.MappedByteBuffer;
import java.nio.channels.FileChannel;
import java.util.ArrayList;
import java.util.HashMap;
import java.util.HexFormat;
import java.util.List;
import java.util.Map;
import java.util.concurrent.ConcurrentHashMap;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicLong;
import java.util.logging.Logger;
import org.newsclub.net.unix.AFUNIXSocket;
import org.newsclub.net.unix.FileDescriptorCast;

/**
 * One session with a server's shared memory, after its WELCOME (docs/client-protocol.md, "Large
 * values by shared memory"). It
 *
 * <ul>
 *   <li><em>stages</em> a large value: copies it into a free region of the staging area, which a
 *       write then names ({@code StagedValue}); the region is reused once the write's reply came,
 *       never while its outcome is unknown ({@link ShmStaging});
 *   <li><em>claims</em> a value the server lent ({@code SharedValue} in an entry): a read-only
 *       buffer over the segment it is in (mapped once, when its SEGMENT frame came) and a {@link
 *       Lease} that gives it back (RELEASE) when its last holder lets go;
 *   <li>counts the references each read call received and says so (RECEIVED), so that the
 *       server takes back what never arrived ({@link ReadCall});
 *   <li>hands a watch call's EVENTS frames to the {@link EventsHandler} of that call (docs/client-protocol.md,
 *       "A watch's events on the session's socket");
 *   <li>carries the component's writes to that server, once it has the session: WRITES frames out,
 *       REPLIES frames in ({@link SessionWrites}; docs/client-protocol.md, "Writes on the session's
 *       socket"), as the identity of the token its HELLO carried ({@link #token}); and its gets,
 *       when the server answers them there ({@link #reads}).
 * </ul>
 *
 * <p>Its socket's threads, which thread reads and which writes when, are {@link SessionSocket}'s.
 * Whichever thread reads runs an EVENTS frame's handler itself, which queues the changes on the
 * component's dispatcher: from the kernel to the dispatcher's queue on one thread; it answers the
 * writes of a REPLIES frame after the EVENTS frames before it (the server sends a write's events
 * before its reply), and while a write waits for its reply it queues events over the dispatcher's
 * capacity rather than wait for room ({@link
 * #mustRead}). Segments are mapped with {@link FileChannel#map}; a segment the server retired,
 * or every segment once the session ended, is unmapped as soon as no lease of it is held (the
 * memory of a dead server goes at once, not at some later garbage collection). So a buffer taken
 * from a view must not be read after the view was closed: its memory may be gone. The staging area
 * is unmapped when the session ends, or once the last {@link Loan} whose buffer is in it was written
 * or closed. The twin of
 * python/cast/client/shm_session.py and cpp_client/src/shm_session.cc; {@link SharedLink}
 * opens it.
 */
final class SharedSession {
  private static final Logger LOG = Logger.getLogger("cast.client");
  static final String METADATA_KEY = "cast-shared-memory";
  /** How long a claim waits for the SEGMENT frame that was sent before the message naming it. */
  static final long SEGMENT_WAIT_MS = 5000;
  /** A long read call says what it received this often, so the server forgets the rest. */
  static final int RECEIVED_EVERY = 64;

  final byte[] id;
  final String idHex;
  final String serverId;
  final long threshold;
  final long window;
  final String endpoint;
  /** The token its HELLO carried: the identity of the writes on its socket. */
  final String token;
  /**
   * The server answers gets in WRITES frames ({@code SharedMemoryInfo.reads}, set by {@link
   * SharedLink#connect}): a component's get goes on this socket. False from a server of an older
   * release, which would refuse a get as an empty request: the unary Get then.
   */
  volatile boolean reads;
  private final AFUNIXSocket socket;
  private final SessionSocket io; // who reads the socket and who writes it
  private final SessionWrites writes;
  private final ShmStaging staging;
  private final Object lock = new Object(); // segments, dead, calls
  private final Map<Long, Segment> segments = new HashMap<>(); // mapped, by id
  private long calls;
  private volatile String dead; // why the session ended, null while it lives
  // call number -> what takes that watch call's EVENTS frames (run on the reader thread)
  private final Map<Long, EventsHandler> eventHandlers = new ConcurrentHashMap<>();
  private int segmentWaiters; // threads waiting in awaitSegment; guarded by lock
  /** EVENTS frames read on this session (for tests and diagnostics). */
  final AtomicLong eventFrames = new AtomicLong();

  /**
   * What takes one watch call's EVENTS frames: {@link #frame} runs on the session's reader
   * thread, one frame at a time in the order read (it may wait for room in the dispatcher's
   * queue: the socket, then the server, hold the rest meanwhile); {@link #sessionEnded} once,
   * when the session ends while the handler is registered.
   */
  interface EventsHandler {
    /** One EVENTS frame of the call: its serialized WatchResponse. */
    void frame(ByteBuffer response);

    /** The session ended ({@code why}): the server ends the call; no more frames come. */
    void sessionEnded(String why);
  }

  /**
   * The session of a socket whose WELCOME ({@code welcome}, with the staging area's {@code
   * stagingFd}) came in answer to a HELLO with {@code token}.
   */
  SharedSession(
      AFUNIXSocket socket, ShmWire.Welcome welcome, FileDescriptor stagingFd, String endpoint, String token)
      throws IOException {
    this.socket = socket;
    this.token = token;
    this.writes = new SessionWrites(this, endpoint);
    this.io =
        new SessionSocket(
            socket,
            endpoint,
            new SessionSocket.Owner() {
              @Override
              public void handle(ShmWire.Frame frame) {
                SharedSession.this.handle(frame);
              }

              @Override
              public void end(String why) {
                SharedSession.this.end(why);
              }

              @Override
              public void readerLeft() {
                writes.readerLeft();
              }
            },
            welcome.version() >= ShmWire.NUDGE_VERSION);
    this.id = welcome.session();
    this.idHex = HexFormat.of().formatHex(id);
    this.serverId = HexFormat.of().formatHex(welcome.serverId());
    this.threshold = welcome.threshold();
    this.window = welcome.window();
    this.endpoint = endpoint;
    this.staging = new ShmStaging(mapReadWrite(stagingFd, welcome.staging()));
  }

  /**
   * Start reading and sending (once the session passed the client's checks): {@link
   * SessionSocket} says which thread reads and writes when.
   */
  void start(List<ShmWire.Frame> already, ShmWire.Reader reader, InputStream in, OutputStream out) {
    for (ShmWire.Frame f : already) {
      handle(f);
    }
    io.start(reader, in, out);
  }

  /** Who reads this session's socket and who writes it. */
  SessionSocket io() {
    return io;
  }

  /** Why the session ended, or null while it lives. */
  String dead() {
    return dead;
  }

  /** The component's Write-stream requests on this session's socket. */
  SessionWrites writes() {
    return writes;
  }

  /** A segment as mapped here, and how many leases of its values are held. */
  private static final class Segment {
    final MappedByteBuffer map; // the mapping itself: what is unmapped
    final ByteBuffer bytes; // read-only, what values are cut from
    int held; // leases not given back; guarded by the session's lock
    boolean retired; // no value of it will be lent again; guarded by the session's lock

    Segment(MappedByteBuffer map) {
      this.map = map;
      this.bytes = map.asReadOnlyBuffer();
    }
  }

  // ------------------------------------------------------------------ writes

  /** {@code value} copied into a free region of the staging area; null when there is none (send the bytes). */
  ShmStaging.Staged stage(ByteString value) {
    return dead != null ? null : staging.stage(value);
  }

  /** What a write request says of a staged value. */
  StagedValue stagedValue(ShmStaging.Staged staged) {
    return StagedValue.newBuilder()
        .setSession(ByteString.copyFrom(id))
        .setOffset(staged.offset())
        .setSize(staged.size())
        .build();
  }

  /** The write's reply came ({@code known}): its region is free again; else it stays taken (ShmStaging.unstage). */
  void unstage(ShmStaging.Staged staged, boolean known) {
    staging.unstage(staged, known);
  }

  /** Bytes of staged values whose write's outcome is unknown: never written again while the session lives. */
  long quarantined() {
    return staging.quarantined();
  }

  /**
   * A region of the staging area lent to a loan, {@code header} written in it and room for {@code
   * size} bytes of payload after it ({@link ShmStaging#lend}); null when there is none or the
   * session ended (the loan is then private memory).
   */
  ShmStaging.Lent lend(ByteString header, int size) {
    return dead != null ? null : staging.lend(header, size);
  }

  /** What a write request says of a loan's value, named where it is. */
  StagedValue stagedValue(ShmStaging.Lent loan) {
    return StagedValue.newBuilder()
        .setSession(ByteString.copyFrom(id))
        .setOffset(loan.offset())
        .setSize(loan.size())
        .build();
  }

  /** The staging area (loans give their regions back to it; tests read it). */
  ShmStaging staging() {
    return staging;
  }

  // ------------------------------------------------------------------- reads

  /**
   * One read call (a Get, a Watch stream, a get on this socket) on this session: its metadata
   * names it, or a get's {@code read_call}.
   */
  final class ReadCall {
    final long number;
    private long count; // guarded by this
    private boolean ended; // guarded by this

    private ReadCall(long number) {
      this.number = number;
    }

    /** The value of the call's {@value #METADATA_KEY} metadata. */
    String metadata() {
      return idHex + "/" + number;
    }

    SharedSession session() {
      return SharedSession.this;
    }

    /**
     * The bytes of a value lent on this call, and its lease (held once); UnavailableError if they
     * cannot be read, or if the call already ended (its RECEIVED was sent without it, so the server
     * takes it back itself).
     */
    Lease claim(SharedValue ref) {
      long n;
      synchronized (this) {
        if (ended) {
          throw new UnavailableError("read call " + number + " of the shared-memory session with " + endpoint
              + " has ended: its values are given back by the server; read again");
        }
        n = ++count;
      }
      if (n % RECEIVED_EVERY == 0) {
        send(ShmWire.received(number, n, false));
      }
      return SharedSession.this.claim(ref);
    }

    /**
     * The call is over: the server takes back what it sent on it and this call never received.
     * {@code answered}: the whole answer was read, so with no reference in it there is nothing
     * to say.
     */
    void end(boolean answered) {
      long n;
      synchronized (this) {
        if (ended) {
          return;
        }
        ended = true;
        n = count;
      }
      if (n > 0 || !answered) {
        send(ShmWire.received(number, n, true));
      }
    }
  }

  /**
   * {@code handler} takes the EVENTS frames of read call {@code call} from now on; if the session
   * has ended already it is told at once.
   */
  void onEvents(long call, EventsHandler handler) {
    eventHandlers.put(call, handler);
    io.readOn();
    String why = dead;
    if (why != null && eventHandlers.remove(call, handler)) {
      handler.sessionEnded(why);
    }
  }

  /** No more EVENTS frames for read call {@code call}: those that still come are dropped. */
  void offEvents(long call) {
    eventHandlers.remove(call);
  }

  /**
   * Whether a thread waits for a SEGMENT frame: the reader must not then wait for room in a
   * dispatcher's queue (the segment may be behind the EVENTS frame it holds, and the waiter may be
   * the dispatcher's own callback).
   */
  boolean segmentAwaited() {
    synchronized (lock) {
      return segmentWaiters > 0;
    }
  }

  /**
   * Whether the reader must read on rather than wait for room in a dispatcher's queue: a thread
   * waits for a SEGMENT frame ({@link #segmentAwaited}), or a write for its REPLIES frame. Either
   * may be behind the frame the reader holds, and the waiter may be the dispatcher's own callback,
   * which would then wait for the room its own wait keeps from being made.
   */
  boolean mustRead() {
    return writes.outstanding() > 0 || segmentAwaited();
  }

  /** A new read call on this session. */
  ReadCall newCall() {
    synchronized (lock) {
      return new ReadCall(++calls);
    }
  }

  private Lease claim(SharedValue ref) {
    long valueId = ref.getValueId();
    io.readOn(); // the segment may still be in the socket, and the call's next values come with no one waiting
    Segment segment;
    try {
      segment = awaitSegment(ref.getSegment()); // counts the lease held
    } catch (UnavailableError e) {
      giveBack(valueId, null); // the server counted it lent
      throw e;
    }
    long end = ref.getOffset() + ref.getSize();
    if (ref.getOffset() < 0 || ref.getSize() < 0 || end > segment.bytes.capacity()) {
      giveBack(valueId, segment);
      throw new UnavailableError(
          "the server at " + endpoint + " named bytes " + ref.getOffset() + ".." + end + " of shared-memory segment "
              + ref.getSegment() + ", which has " + segment.bytes.capacity() + ": read again");
    }
    ByteBuffer bytes = segment.bytes.duplicate().position((int) ref.getOffset()).limit((int) end).slice();
    return new Lease(bytes, () -> giveBack(valueId, segment));
  }

  /** The segment named, once its SEGMENT frame came, with one more lease of it held. */
  private Segment awaitSegment(long segmentId) {
    // Sent before the message naming it: it is in the socket already, or comes at once. The reader
    // thread reads for the wait: the dispatcher, which may read the socket itself, may be the waiter.
    long deadline = System.nanoTime() + TimeUnit.MILLISECONDS.toNanos(SEGMENT_WAIT_MS);
    boolean readerAsked = false;
    try {
      synchronized (lock) {
        while (true) {
          Segment segment = segments.get(segmentId);
          if (segment != null) {
            segment.held++;
            return segment;
          }
          long left = deadline - System.nanoTime();
          if (dead != null || left <= 0) {
            throw new UnavailableError(
                "shared-memory segment " + segmentId + " of the server at " + endpoint + " did not arrive ("
                    + (dead != null ? dead : "within " + SEGMENT_WAIT_MS / 1000.0 + " s") + "): read again");
          }
          if (!readerAsked) {
            readerAsked = true;
            io.readFor();
          }
          segmentWaiters++;
          try {
            TimeUnit.NANOSECONDS.timedWait(lock, left);
          } catch (InterruptedException e) {
            Thread.currentThread().interrupt();
            throw new UnavailableError("interrupted while waiting for shared-memory segment " + segmentId);
          } finally {
            segmentWaiters--;
          }
        }
      }
    } finally {
      if (readerAsked) {
        io.readDone();
      }
    }
  }

  /**
   * A lease's last holder let go: RELEASE it ({@link SessionSocket#giveBack}; nothing once the
   * session ended), and unmap its segment if that was retired and this was its last lease.
   */
  private void giveBack(long valueId, Segment segment) {
    boolean unmap = false;
    synchronized (lock) {
      if (segment != null) {
        segment.held--;
        unmap = segment.retired && segment.held == 0;
      }
    }
    if (dead == null) {
      io.giveBack(valueId);
    }
    if (unmap) {
      ShmStaging.unmap(segment.map);
    }
  }

  // ------------------------------------------------------------------ frames

  /** Write {@code frame} to the socket from this thread, whole ({@link SessionSocket#sendNow}). */
  void sendNow(byte[] frame) {
    io.sendNow(frame);
  }

  /** Queue a frame for the sender thread (nothing once the session ended). */
  void send(byte[] frame) {
    io.send(frame);
  }

  private void handle(ShmWire.Frame frame) {
    try {
      switch (frame.kind()) {
        case ShmWire.SEGMENT -> {
          long[] f = ShmWire.parseSegment(frame.body());
          Segment segment = new Segment(mapReadOnly(frame.fd(), f[1]));
          Segment old;
          synchronized (lock) {
            old = segments.put(f[0], segment);
            lock.notifyAll();
          }
          if (old != null) {
            retire(old); // the server never sends a live segment twice; if it did, the old one goes
          }
        }
        case ShmWire.RETIRE -> {
          Segment segment;
          synchronized (lock) {
            segment = segments.remove(ShmWire.parseRetire(frame.body()));
          }
          if (segment != null) {
            retire(segment);
          }
        }
        case ShmWire.EVENTS -> {
          long call = ShmWire.parseEventsCall(frame.body());
          eventFrames.incrementAndGet();
          EventsHandler handler = eventHandlers.get(call);
          if (handler != null) { // else the call ended: its values, never claimed, the server takes back
            try {
              handler.frame(frame.body());
            } catch (RuntimeException e) { // one watch call's trouble must not end the session of the others
              LOG.severe("the events of watch call " + call + " from " + endpoint + " failed: " + e);
            }
          }
        }
        case ShmWire.REPLIES -> writes.replies(frame.body());
        case ShmWire.NUDGED -> {} // it woke the thread that read it: nothing more
        case ShmWire.REFUSED -> end("the server ended it: " + ShmWire.text(frame.body()));
        default -> closeAll(frame.fd()); // a kind this client does not know: ignored
      }
    } catch (ShmWire.ProtocolError | IOException e) {
      closeAll(frame.fd());
      end(e.getMessage());
    }
  }

  /** No value of {@code segment} will be lent again: unmap it now if none is held, else when the last goes. */
  private void retire(Segment segment) {
    boolean unmap;
    synchronized (lock) {
      segment.retired = true;
      unmap = segment.held == 0;
    }
    if (unmap) {
      ShmStaging.unmap(segment.map);
    }
  }

  /** End the session: the server gives back everything it lent it. Idempotent. */
  void end(String why) {
    List<Segment> mapped;
    synchronized (lock) {
      if (dead != null) {
        return;
      }
      dead = why == null ? "closed" : why;
      mapped = new ArrayList<>(segments.values());
      segments.clear();
      lock.notifyAll(); // claims waiting for a segment see the end
    }
    mapped.forEach(this::retire); // each unmapped once no value of it is held
    LOG.fine("shared-memory session with " + endpoint + " ended: " + why);
    writes.ended(dead); // what is outstanding may or may not have been applied
    for (Long call : List.copyOf(eventHandlers.keySet())) {
      EventsHandler handler = eventHandlers.remove(call);
      if (handler != null) {
        handler.sessionEnded(dead);
      }
    }
    io.close();
    staging.close();
  }

  // ---------------------------------------------------------------- mappings

  /** A descriptor's number (for /proc/self/fd), through junixsocket. */
  private static int number(FileDescriptor fd) throws IOException {
    return FileDescriptorCast.using(fd).as(Integer.class);
  }

  /** The staging area mapped read-write and shared; its descriptor is closed (the mapping keeps the memory file). */
  static MappedByteBuffer mapReadWrite(FileDescriptor fd, long size) throws IOException {
    try {
      if (size <= 0 || size > Integer.MAX_VALUE) {
        throw new IOException("a staging area of " + size + " bytes (a Java mapping holds at most 2 GiB)");
      }
      // A channel of a descriptor alone is read-only or write-only; its /proc path opens the memory file both ways.
      try (RandomAccessFile file = new RandomAccessFile("/proc/self/fd/" + number(fd), "rw")) {
        return file.getChannel().map(FileChannel.MapMode.READ_WRITE, 0, size);
      }
    } finally {
      closeAll(fd);
    }
  }

  /** A segment mapped read-only and shared; its descriptor is closed. */
  static MappedByteBuffer mapReadOnly(FileDescriptor fd, long size) throws IOException {
    try (FileInputStream in = new FileInputStream(fd)) {
      if (size <= 0 || size > Integer.MAX_VALUE) {
        throw new IOException("a shared-memory segment of " + size + " bytes (a Java mapping holds at most 2 GiB)");
      }
      return in.getChannel().map(FileChannel.MapMode.READ_ONLY, 0, size);
    }
  }

  /** Close descriptors (null ones are skipped). */
  static void closeAll(FileDescriptor... fds) {
    if (fds == null) {
      return;
    }
    for (FileDescriptor fd : fds) {
      if (fd != null && fd.valid()) {
        try {
          new FileInputStream(fd).close();
        } catch (IOException e) {
          LOG.fine("closing a descriptor: " + e.getMessage());
        }
      }
    }
  }
}
