package cast.client;

import java.io.FileDescriptor;
import java.io.IOException;
import java.io.InputStream;
import java.io.OutputStream;
import java.util.ArrayDeque;
import java.util.ArrayList;
import java.util.List;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicInteger;
import java.util.concurrent.atomic.AtomicLong;
import java.util.concurrent.locks.ReentrantLock;
import java.util.function.BooleanSupplier;
import java.util.logging.Logger;
import org.newsclub.net.unix.AFUNIXSocket;

/**
 * The Unix socket of one shared-memory session (docs/client-protocol.md, "Large values by shared
 * memory"): which thread reads it and which writes it. What the frames mean is the {@link Owner}'s
 * ({@link SharedSession}).
 *
 * <p>Reading. One thread at a time reads, holding {@link #reading}, and handles every frame of what
 * it read before it lets go, so frames are handled in the order they came. A thread waiting for
 * its write's reply reads it itself when no other thread reads ({@link #readUntil}), as the Python
 * and C++ clients' waiting threads do, rather than be woken by a reader thread that read it. The
 * reader thread reads whenever something may come that no thread waits for: from the start, until
 * writes that threads wait for come (it then leaves the socket to them, and reads again once they
 * paused for {@link #WRITER_PAUSE_MS}, so that a server that dies is noticed and its memory let go
 * without another write); while a lock request waits, since a thread blocked in the socket's read
 * cannot be interrupted and a lock may wait long ({@link #readFor}); all the time once a watch's
 * events, a read call's values or a write nobody waits for may come ({@link #readOn}). Once the
 * component's dispatcher reads the socket itself ({@link Dispatcher#attach}, with a server that
 * answers NUDGE), it reads while it has nothing to run and the reader thread is its standby: it
 * reads while a lock request or a claim waits ({@link #readFor}) and while one of the dispatcher's
 * calls runs longer than {@link #STANDBY_MS}, looking every {@link #STANDBY_MS} while the
 * dispatcher is busy and asleep once it was idle for {@link #IDLE_MS}. Reads block with no timeout
 * (junixsocket's read timeout would bound the socket's writes too): the session's end closes the
 * socket, which ends them, and a NUDGE the server answers wakes the dispatcher's.
 *
 * <p>Writing. One frame at a time, whole, holding {@link #writing}: a write's WRITES frame by the
 * thread that sends the write ({@link #sendNow}), a RELEASE by the thread that let the value go
 * when no other is writing ({@link #giveBack}), the rest (RECEIVED, and a RELEASE while another
 * thread was writing) by the sender thread, so that giving a value back never waits for another
 * thread's frame.
 */
final class SessionSocket implements Dispatcher.Source {
  private static final Logger LOG = Logger.getLogger("cast.client");

  /**
   * How long the writes that threads wait for must pause before the reader thread reads the
   * socket again (while it does, such a write is answered by it instead of reading its reply
   * itself: one wake-up more).
   */
  static final long WRITER_PAUSE_MS = 100;

  /** How long one of the dispatcher's calls may run before the reader thread reads the socket in its place. */
  static final long STANDBY_MS = 10;

  /** How long the dispatcher must have been idle before the reader thread stops looking every STANDBY_MS. */
  static final long IDLE_MS = 1000;

  /** What a read asks for at least: a reply, an event's frame or a few of them; more when more is waiting. */
  static final int SMALL_READ = 2048;

  /** What the session does with the socket's frames and its failures. */
  interface Owner {
    /** A frame read, on the thread that read it, in the order read. */
    void handle(ShmWire.Frame frame);

    /** The socket failed or the server closed it ({@code why}): the session ends (and closes this). */
    void end(String why);

    /** A thread stopped reading: the writes waiting for another thread to read look again. */
    void readerLeft();
  }

  private final AFUNIXSocket socket;
  private final String endpoint;
  private final Owner owner;
  // Held while a frame is written (frames whole); a lock rather than a monitor for giveBack's tryLock.
  private final ReentrantLock writing = new ReentrantLock();
  private volatile OutputStream out; // set by start
  // Held by the thread that reads; the three below are used under it only.
  private final ReentrantLock reading = new ReentrantLock();
  private ShmWire.Reader frames; // set by start
  private InputStream in; // set by start
  private byte[] readBuffer; // made by the first read
  private boolean lastReadFilled; // the last read gave all it asked for: more is likely waiting
  private final Object queue = new Object(); // the outbox, what was given back, the reader's pause
  private final ArrayDeque<byte[]> outbox = new ArrayDeque<>(); // guarded by queue
  private final List<Long> givenBack = new ArrayList<>(); // value ids to RELEASE; guarded by queue
  private volatile boolean closed;
  private final boolean nudges; // the server answers NUDGE: a dispatcher may read the socket (Dispatcher.attach)
  // The dispatcher that reads the socket while idle (the reader thread is its standby), or null.
  private volatile Dispatcher dispatcher;
  private volatile boolean standbyAsleep; // the reader thread waits with no timeout, the dispatcher idle; set under queue
  // The reader thread reads all the time: something may come that no thread waits for. Set once, by readOn.
  private volatile boolean readAlways;
  // Requests whose waiting thread does not read (locks, which may wait long): the reader thread reads meanwhile.
  private final AtomicInteger readingFor = new AtomicInteger();
  // System.nanoTime() when a write that a thread waits for was last sent (long before, at first).
  private volatile long lastWaited = System.nanoTime() - TimeUnit.MILLISECONDS.toNanos(2 * WRITER_PAUSE_MS);
  /** Bytes the socket's reads asked for, in all (for tests and diagnostics: see {@link #readLength}). */
  final AtomicLong bytesAsked = new AtomicLong();
  /** Reads by threads waiting for their write's reply (for tests and diagnostics). */
  final AtomicLong waiterReads = new AtomicLong();
  /** Reads by the dispatcher's thread ({@link #read}, for tests and diagnostics). */
  final AtomicLong dispatcherReads = new AtomicLong();
  /** Reads by the reader thread (for tests and diagnostics). */
  final AtomicLong readerReads = new AtomicLong();
  /** NUDGE frames sent (for tests and diagnostics). */
  final AtomicLong nudgesSent = new AtomicLong();
  /** RELEASE frames sent by the thread that let the values go (for tests and diagnostics). */
  final AtomicLong releasesInline = new AtomicLong();
  /** RELEASE frames sent by the sender thread, another thread writing then (for tests and diagnostics). */
  final AtomicLong releasesBySender = new AtomicLong();

  /**
   * The socket of a session with the server at {@code endpoint}, whose frames go to {@code owner};
   * {@code nudges}: the server answers NUDGE (its WELCOME's version).
   */
  SessionSocket(AFUNIXSocket socket, String endpoint, Owner owner, boolean nudges) {
    this.socket = socket;
    this.nudges = nudges;
    this.endpoint = endpoint;
    this.owner = owner;
  }

  /** Start the reader and sender threads, on the socket's streams and what remains of its {@code reader}. */
  void start(ShmWire.Reader reader, InputStream in, OutputStream out) {
    this.out = out;
    reading.lock();
    try {
      this.frames = reader;
      this.in = in;
    } finally {
      reading.unlock();
    }
    Thread r = new Thread(this::readLoop, "cast-shm-read-" + endpoint);
    r.setDaemon(true);
    r.start();
    Thread s = new Thread(this::sendLoop, "cast-shm-send-" + endpoint);
    s.setDaemon(true);
    s.start();
  }

  // ----------------------------------------------------------------- reading

  /**
   * From now on the reader thread reads all the time: something may come that no thread waits
   * for (a watch's events, the segment a read call's value is in, the replies of writes nobody
   * waits for).
   */
  void readOn() {
    if (!readAlways) {
      synchronized (queue) {
        readAlways = true;
        queue.notifyAll(); // the reader thread, waiting for the writers' pause
      }
    }
  }

  /** Whether the reader thread reads all the time now (for tests and diagnostics). */
  boolean readsAlways() {
    return readAlways;
  }

  /** A write that a thread will wait for is being sent: that thread reads its reply. */
  void waitedWriteSent() {
    lastWaited = System.nanoTime();
  }

  /**
   * A request is being sent whose waiting thread will not read its reply (a lock, which may wait
   * long: a thread blocked in the socket's read cannot be interrupted): the reader thread reads
   * until {@link #readDone}.
   */
  void readFor() {
    if (readingFor.getAndIncrement() == 0) {
      synchronized (queue) {
        queue.notifyAll(); // the reader thread, waiting for the writers' pause
      }
    }
  }

  /** The reply of a request {@link #readFor} was for came (or never will). */
  void readDone() {
    readingFor.decrementAndGet();
  }

  /** Whether a thread reads the socket now (it says so when it stops: {@link Owner#readerLeft}). */
  boolean reading() {
    return reading.isLocked();
  }

  /**
   * Read and handle what comes, on this thread, until {@code done} or the socket closed; false at
   * once when another thread reads (it handles what comes). A reply past its deadline ends the
   * session ({@link SessionWrites}), which closes the socket and so ends the read.
   */
  boolean readUntil(BooleanSupplier done) {
    if (closed) {
      return true;
    }
    if (!reading.tryLock()) {
      return false;
    }
    try {
      while (!closed && !done.getAsBoolean()) {
        waiterReads.incrementAndGet();
        if (!readOrEnd()) {
          break;
        }
      }
    } finally {
      stopReading();
    }
    return true;
  }

  /** Let the socket go: a writer waiting for a reader reads next; what a closed socket left is closed. */
  private void stopReading() {
    try {
      if (closed && frames != null) {
        SharedSession.closeAll(frames.stray().toArray(new FileDescriptor[0]));
      }
    } finally {
      reading.unlock();
      owner.readerLeft();
      Dispatcher d = dispatcher;
      if (d != null) {
        d.sourceFree(); // it may wait to read because this thread did
      }
    }
  }

  private void readLoop() {
    // One read per call of readTurn: the JIT compiles a method by its calls, but this loop, entered
    // once, only by its back-edges (tens of thousands), so a frame's work kept in it ran in the
    // bytecode interpreter for the whole of M8's phase (docs/performance-m8.md, "The Java watcher's
    // loops in the interpreter").
    while (!closed && (writersPause() || readTurn())) {
      // every frame of the read is handled
    }
  }

  /**
   * While writes that threads wait for come, and nothing else needs the reader, wait until they
   * paused for {@link #WRITER_PAUSE_MS} (or something needs it); true if it waited. While a
   * dispatcher reads the socket, stand by instead ({@link #standBy}).
   */
  private boolean writersPause() {
    Dispatcher d = dispatcher;
    if (d != null) {
      return standBy(d);
    }
    long left = TimeUnit.MILLISECONDS.toNanos(WRITER_PAUSE_MS) - (System.nanoTime() - lastWaited);
    if (readAlways || left <= 0 || readingFor.get() > 0) {
      return false;
    }
    synchronized (queue) {
      if (!readAlways && !closed && readingFor.get() == 0) {
        try {
          TimeUnit.NANOSECONDS.timedWait(queue, left);
        } catch (InterruptedException e) {
          owner.end("interrupted");
        }
      }
    }
    return true;
  }

  /**
   * The reader thread as the standby of dispatcher {@code d}, which reads the socket while idle:
   * false (read now) while a request it reads for waits, or while {@code d}'s call runs longer than
   * {@link #STANDBY_MS}; else wait (true): until that call's time is up, {@link #STANDBY_MS} while
   * {@code d} was busy lately, with no timeout once it was idle for {@link #IDLE_MS} (its next call
   * wakes this thread: {@link #callBegan}).
   */
  private boolean standBy(Dispatcher d) {
    if (readingFor.get() > 0) {
      return false;
    }
    long standby = TimeUnit.MILLISECONDS.toNanos(STANDBY_MS);
    long now = System.nanoTime();
    long started = d.callStarted();
    if (started != 0 && now - started >= standby) {
      return false;
    }
    synchronized (queue) {
      if (closed || readingFor.get() > 0 || dispatcher != d) {
        return true;
      }
      try {
        if (started != 0) {
          TimeUnit.NANOSECONDS.timedWait(queue, started + standby - now);
        } else if (now - d.lastCallEnded() < TimeUnit.MILLISECONDS.toNanos(IDLE_MS)) {
          TimeUnit.NANOSECONDS.timedWait(queue, standby);
        } else {
          standbyAsleep = true;
          // Read again after saying so: a call that began before it was said is seen here, one after wakes it.
          if (d.callStarted() == 0) {
            queue.wait();
          }
        }
      } catch (InterruptedException e) {
        owner.end("interrupted");
      } finally {
        standbyAsleep = false;
      }
    }
    return true;
  }

  /** One read of the reader thread, holding the socket meanwhile; false once the socket closed. */
  private boolean readTurn() {
    reading.lock();
    try {
      readerReads.incrementAndGet();
      return !closed && readOrEnd();
    } finally {
      stopReading();
    }
  }

  /**
   * One read and its frames (holding {@link #reading}); a read that fails ends the session, as the
   * server's end does in {@link #readOnce}. False once the socket closed or failed.
   */
  private boolean readOrEnd() {
    String failed;
    try {
      return readOnce();
    } catch (IOException e) {
      failed = "read failed: " + e.getMessage();
    } catch (ShmWire.ProtocolError e) {
      failed = e.getMessage();
    }
    owner.end(failed);
    return false;
  }

  /** One read and the frames it completed (holding {@link #reading}); false once the server closed the socket. */
  private boolean readOnce() throws IOException, ShmWire.ProtocolError {
    if (readBuffer == null) {
      readBuffer = new byte[ShmWire.MAX_FRAME];
    }
    int asked = readLength();
    int n = in.read(readBuffer, 0, asked);
    FileDescriptor[] fds = socket.getReceivedFileDescriptors();
    if (n < 0) {
      SharedSession.closeAll(fds);
      owner.end("the server closed the session");
      return false;
    }
    bytesAsked.addAndGet(asked);
    lastReadFilled = n == asked;
    for (ShmWire.Frame frame : frames.feed(readBuffer, n, fds)) {
      owner.handle(frame);
    }
    return true;
  }

  /**
   * How many bytes the next read asks for (holding {@link #reading}): what the frame begun still
   * needs, at least {@link #SMALL_READ}, or the whole buffer after a read that filled what it
   * asked (more is likely waiting). junixsocket copies as many bytes as a read asks for into the
   * array, whatever the socket gave: a 64 KiB read for a 30-byte reply copied 64 KiB every time
   * (docs/performance.md, "The Java client's reads").
   */
  private int readLength() {
    int want = Math.max(frames.wanted(), lastReadFilled ? ShmWire.MAX_FRAME : SMALL_READ);
    return Math.min(want, ShmWire.MAX_FRAME);
  }

  // ------------------------------------------------ read by the dispatcher

  /** Whether the server answers NUDGE, so that a dispatcher may read this socket ({@link Dispatcher#attach}). */
  boolean nudges() {
    return nudges;
  }

  /**
   * One read on this thread (the dispatcher's) and its frames: at once if bytes are there, else
   * only without {@code onlyIfReady}, blocked until something comes (a frame, a NUDGE's answer,
   * the socket's end). False at once when another thread reads.
   */
  @Override
  public boolean read(boolean onlyIfReady) {
    if (closed) {
      return true;
    }
    if (!reading.tryLock()) {
      return false;
    }
    try {
      if (!closed && (!onlyIfReady || ready())) {
        dispatcherReads.incrementAndGet();
        readOrEnd();
      }
    } finally {
      stopReading();
    }
    return true;
  }

  /** Whether bytes wait in the socket (holding {@link #reading}); true when it cannot tell (the read will say why). */
  private boolean ready() {
    try {
      return in.available() > 0;
    } catch (IOException e) {
      return true;
    }
  }

  @Override
  public void nudge() {
    nudgesSent.incrementAndGet();
    send(ShmWire.nudge());
  }

  @Override
  public boolean ended() {
    return closed;
  }

  @Override
  public void dispatched(Dispatcher d) {
    synchronized (queue) {
      dispatcher = d;
      queue.notifyAll(); // the reader thread: to stand by, or to read again
    }
  }

  @Override
  public void callBegan() {
    if (standbyAsleep) {
      synchronized (queue) {
        queue.notifyAll();
      }
    }
  }

  /** The dispatcher that reads the socket while idle, or null (for tests and diagnostics). */
  Dispatcher dispatcher() {
    return dispatcher;
  }

  // ----------------------------------------------------------------- writing

  /**
   * Write {@code frame} from this thread, whole, after any frame being written (nothing once the
   * socket closed). A write that fails ends the session.
   */
  void sendNow(byte[] frame) {
    if (closed) {
      return;
    }
    writing.lock();
    writeAndLetGo(List.of(frame));
  }

  /** Queue a frame for the sender thread (nothing once the socket closed). */
  void send(byte[] frame) {
    synchronized (queue) {
      if (!closed) {
        outbox.add(frame);
        queue.notifyAll();
      }
    }
  }

  /**
   * Give value {@code valueId} back (RELEASE): from this thread when no other is writing, as the
   * Python and C++ clients do, rather than wake the sender thread for every value a watcher lets
   * go; else the sender thread sends it (it is woken), so that letting a value go never waits for
   * another thread's write.
   */
  void giveBack(long valueId) {
    synchronized (queue) {
      if (closed) {
        return;
      }
      givenBack.add(valueId);
    }
    if (!writing.tryLock()) {
      synchronized (queue) {
        queue.notifyAll();
      }
      return;
    }
    List<byte[]> releases;
    synchronized (queue) {
      if (closed || givenBack.isEmpty()) {
        writing.unlock();
        return; // sent meanwhile by the sender thread
      }
      releases = takeReleases();
    }
    releasesInline.addAndGet(releases.size());
    writeAndLetGo(releases);
  }

  /** The RELEASE frames of what was given back, which is then forgotten (holding {@link #queue}). */
  private List<byte[]> takeReleases() {
    List<byte[]> releases = ShmWire.release(givenBack); // gathered: many leases, one frame
    givenBack.clear();
    return releases;
  }

  /**
   * Write {@code frames}, whole, then let {@link #writing} go (the caller took it); a write that
   * fails ends the session.
   */
  private void writeAndLetGo(List<byte[]> frames) {
    String failed = null;
    try {
      for (byte[] f : frames) {
        out.write(f);
      }
      out.flush();
    } catch (IOException e) {
      failed = "write failed: " + e.getMessage();
    } finally {
      writing.unlock();
    }
    if (failed != null) {
      owner.end(failed);
    }
  }

  private void sendLoop() {
    try {
      while (sendOnce()) { // a method per turn, as readTurn, so that the JIT compiles it
        // what was queued is sent
      }
    } catch (InterruptedException e) {
      owner.end("interrupted");
    }
  }

  /** Wait for frames to send and send them; false once the socket closed. */
  private boolean sendOnce() throws InterruptedException {
    List<byte[]> sending;
    synchronized (queue) {
      while (!closed && outbox.isEmpty() && givenBack.isEmpty()) {
        queue.wait();
      }
      if (closed) {
        return false;
      }
      sending = takeReleases();
      releasesBySender.addAndGet(sending.size());
      sending.addAll(outbox);
      outbox.clear();
    }
    writing.lock();
    writeAndLetGo(sending);
    return true;
  }

  // ------------------------------------------------------------------- end

  /**
   * Close the socket (the session ended): nothing more is sent, the thread reading sees its end,
   * the descriptors of a frame cut short are closed. Idempotent.
   */
  void close() {
    synchronized (queue) {
      closed = true;
      givenBack.clear();
      outbox.clear();
      queue.notifyAll(); // the sender, and the reader waiting for the writers' pause, see the end
    }
    try {
      socket.close();
    } catch (IOException e) {
      LOG.fine("closing the shared-memory socket: " + e.getMessage());
    }
    // Else the thread reading (this one, maybe, inside a frame's handling) sees the end and does it.
    if (!reading.isHeldByCurrentThread() && reading.tryLock()) {
      stopReading();
    }
  }
}
