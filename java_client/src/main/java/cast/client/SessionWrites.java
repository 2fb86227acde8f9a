package cast.client;

import cast.v1.WriteReplies;
import cast.v1.WriteReply;
import cast.v1.WriteRequest;
import cast.v1.WriteRequests;
import com.google.protobuf.InvalidProtocolBufferException;
import java.nio.ByteBuffer;
import java.time.Duration;
import java.util.ArrayList;
import java.util.HashMap;
import java.util.List;
import java.util.Map;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.ScheduledFuture;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicLong;

/**
 * A component's Write-stream requests on its shared-memory session's Unix socket
 * (docs/client-protocol.md, "Writes on the session's socket"): WRITES frames out, REPLIES frames
 * in. The {@link WriteStream} sends here instead of on its gRPC call while the session with that
 * server lives. The same messages as the Write stream (a {@code WriteRequests}, a {@code
 * WriteReplies}), the same rules: replies matched by id, out of order when a lock waits. A get goes
 * here too, as a request a thread waits for ({@link WriteStream#read}), when the server answers
 * gets on the socket. The twin of cpp_client/src/socket_writes.cc; the server's side is
 * python/cast/server/socket_writes.py.
 *
 * <p>A request is written to the socket by the thread that sends it (no hop to another thread on
 * the way out; a socket the server does not read holds the sender back, as a full outbox holds
 * back the gRPC stream's). A thread that waits for its reply reads the REPLIES frame itself when no
 * other thread reads the socket ({@link #await}, {@link SessionSocket#readUntil}), as the Python and
 * C++ clients do; else the thread reading (the session's reader thread, or another waiting writer)
 * answers it and wakes it. A write nobody waits for makes the reader thread read all the time. A
 * request past its deadline fails with DeadlineExceededError and the session is ended, as the
 * Write stream ends its call, so that its other requests fail with UnavailableError ("may or may
 * not have been applied") and the next write opens a new session or goes by gRPC.
 *
 * <p>The deadlines are watched as C++'s reader thread watches them, at the earliest one, but from
 * the gRPC stream's timer thread ({@link WriteCall#DEADLINES}): the reader here blocks in a read
 * that only data or the socket's end wakes (junixsocket's read timeout would also bound the
 * socket's writes, which could then stop halfway through a frame). One task per session, due at
 * its earliest deadline, looks and is scheduled again for the next: a request schedules nothing
 * unless its deadline comes before the task's, so a sequential writer wakes no timer thread per
 * write, as a timer per request would.
 */
final class SessionWrites {
  private final SharedSession session;
  private final String endpoint;
  // All guarded by this.
  private final Map<Long, Pending> pending = new HashMap<>();
  private long lastId;
  private boolean ended;
  private ScheduledFuture<?> watch; // the task that looks at the deadlines, or null
  private long watchAt; // System.nanoTime() when it is due
  private volatile int followers; // threads in await waiting for another thread to read; changed under this
  /** WRITES frames sent on this session (for tests and diagnostics). */
  final AtomicLong framesSent = new AtomicLong();
  /** Bytes of the WRITES frames sent on this session (staged values' not among them; for tests and diagnostics). */
  final AtomicLong bytesSent = new AtomicLong();

  /**
   * A request sent and not answered: where its reply goes; its deadline ({@code at}, in
   * System.nanoTime(), with the {@code timeout} it was and {@code what} the request is; a null
   * timeout: none).
   */
  private record Pending(CompletableFuture<WriteReply> reply, long at, Duration timeout, String what) {}

  /** The writes of {@code session}, with the server at {@code endpoint}. */
  SessionWrites(SharedSession session, String endpoint) {
    this.session = session;
    this.endpoint = endpoint;
  }

  /** The future of a reply to a request sent here: {@link #await} reads it on the waiting thread. */
  static final class Reply extends CompletableFuture<WriteReply> {
    final SessionWrites writes;
    /** The waiting thread reads the reply itself (not for a lock: see {@link SessionSocket#readFor}). */
    final boolean readsItself;

    Reply(SessionWrites writes, boolean readsItself) {
      this.writes = writes;
      this.readsItself = readsItself;
    }
  }

  /**
   * Send {@code request} (its id is set here) in a WRITES frame, from this thread; the future of
   * its reply, or null, with nothing sent, once the session ended. Past {@code deadline} (null:
   * none) the future fails with DeadlineExceededError and the session ends. A frame that cannot be
   * written ends the session, which fails this request with the others. {@code waited}: a thread
   * will wait for the reply ({@link #await}), which reads it itself; else the session's reader
   * thread reads it (and from then on everything).
   */
  Reply send(WriteRequest.Builder request, Duration deadline, boolean waited) {
    // A lock may wait long, and a thread blocked in the socket's read cannot be interrupted: the
    // reader thread reads its reply, and its waiting thread waits on the future as before.
    boolean lock = request.getOperationCase() == WriteRequest.OperationCase.LOCK;
    Reply reply = new Reply(this, waited && !lock);
    long id;
    synchronized (this) {
      if (ended) {
        return null;
      }
      id = ++lastId;
      if (deadline == null) {
        pending.put(id, new Pending(reply, 0, null, null));
      } else {
        long at = System.nanoTime() + deadline.toNanos();
        pending.put(id, new Pending(reply, at, deadline, WriteCall.describe(request)));
        if (watch == null || at - watchAt < 0) {
          watchAt(at);
        }
      }
    }
    byte[] frame;
    try {
      frame = ShmWire.writes(WriteRequests.newBuilder().addRequests(request.setId(id)).build());
    } catch (IllegalArgumentException e) { // the size check before both transports leaves a few bytes of room
      forget(id);
      reply.completeExceptionally(
          new InvalidArgumentError(
              "a write too large for one frame on the shared-memory session with " + endpoint + " was not sent ("
                  + e.getMessage() + "); the server keeps values of at most limits.max_value_bytes (8 MiB by"
                  + " default): store large data elsewhere and keep a reference"));
      return reply;
    }
    if (reply.readsItself) {
      session.io().waitedWriteSent();
    } else if (waited) {
      SessionSocket io = session.io();
      io.readFor();
      reply.whenComplete((r, e) -> io.readDone());
    } else {
      session.io().readOn();
    }
    session.sendNow(frame);
    framesSent.incrementAndGet();
    bytesSent.addAndGet(frame.length);
    return reply;
  }

  /** How long a waiting writer that another thread reads for sleeps before it looks again. */
  private static final long FOLLOW_MS = 50;

  /**
   * Wait until {@code reply} is done: read the socket on this thread while no other thread does;
   * else wait for the thread reading to answer it, or to let the socket go. Interrupted: returns
   * with the thread's interrupt flag set (the caller's {@code get} then says so). A reply that the
   * waiting thread does not read itself (a lock's) is left to the caller's {@code get}.
   */
  void await(Reply reply) {
    while (reply.readsItself && !reply.isDone()) {
      if (session.io().readUntil(reply::isDone)) {
        continue; // answered, or the session ended (which fails it)
      }
      synchronized (this) {
        followers++; // before it looks who reads: a reader leaving now sees it and wakes it
        try {
          while (!reply.isDone() && !ended && session.io().reading()) {
            wait(FOLLOW_MS);
          }
        } catch (InterruptedException e) {
          Thread.currentThread().interrupt();
          return;
        } finally {
          followers--;
        }
      }
    }
  }

  /** A thread stopped reading the socket: the writers waiting for another thread to read look again. */
  void readerLeft() {
    if (followers > 0) {
      synchronized (this) {
        notifyAll();
      }
    }
  }

  /** Request {@code id} will not be answered here after all: no reply is expected for it. */
  private synchronized void forget(long id) {
    pending.remove(id);
    if (pending.isEmpty()) {
      notifyAll();
    }
  }

  /** The deadlines are looked at {@code at} (System.nanoTime()), not at the time scheduled before (holding this). */
  private void watchAt(long at) {
    if (watch != null) {
      watch.cancel(false);
    }
    watchAt = at;
    watch = WriteCall.DEADLINES.schedule(this::expire, at - System.nanoTime(), TimeUnit.NANOSECONDS);
  }

  /** Wait until no request is outstanding (or the session ended), or {@code timeout}. */
  synchronized void drain(Duration timeout) {
    Monitors.waitUntil(this, () -> pending.isEmpty() || ended, timeout);
  }

  /** Requests sent and not yet answered. */
  synchronized int outstanding() {
    return pending.size();
  }

  /**
   * From the thread reading the socket: a REPLIES frame's body answers the requests it names (a
   * request no longer outstanding, whose deadline passed, has its error already).
   */
  void replies(ByteBuffer body) throws ShmWire.ProtocolError {
    WriteReplies message;
    try {
      message = WriteReplies.parseFrom(body);
    } catch (InvalidProtocolBufferException e) {
      throw new ShmWire.ProtocolError("a REPLIES frame is not a cast.v1.WriteReplies (" + e.getMessage() + ")");
    }
    List<CompletableFuture<WriteReply>> answered = new ArrayList<>(message.getRepliesCount());
    synchronized (this) {
      for (WriteReply reply : message.getRepliesList()) {
        Pending p = pending.remove(reply.getId()); // its deadline no longer matters: the watch passes it by
        answered.add(p == null ? null : p.reply());
      }
      if (pending.isEmpty()) {
        notifyAll();
      }
    }
    // Completed outside the lock: a sender waiting in get() wakes here, the futures of the
    // asynchronous writes go on to the component's results thread (WriteStream.submitWrite).
    for (int i = 0; i < answered.size(); i++) {
      if (answered.get(i) != null) {
        answered.get(i).complete(message.getReplies(i));
      }
    }
    if (followers > 0) {
      synchronized (this) {
        notifyAll(); // a writer waiting while this thread read: its reply may be among these
      }
    }
  }

  /** The session ended ({@code why}): nothing more is sent, and what is outstanding fails. */
  void ended(String why) {
    List<Pending> left;
    synchronized (this) {
      if (ended) {
        return;
      }
      ended = true;
      left = new ArrayList<>(pending.values());
      pending.clear();
      if (watch != null) {
        watch.cancel(false);
        watch = null;
      }
      notifyAll();
    }
    if (left.isEmpty()) {
      return;
    }
    UnavailableError error =
        new UnavailableError(
            "the shared-memory session with " + endpoint + " ended (" + why + "): this write may or may not have"
                + " been applied; the client reconnects by itself, retry the call later");
    for (Pending p : left) {
      p.reply().completeExceptionally(error);
    }
  }

  /**
   * The watch is due: the requests past their deadline fail with DeadlineExceededError, and the
   * session ends (a server that answers nothing in that time is hung), failing the others; else
   * the watch is due again at the earliest deadline left.
   */
  private void expire() {
    List<Pending> expired = new ArrayList<>();
    synchronized (this) {
      watch = null;
      if (ended) {
        return;
      }
      long now = System.nanoTime();
      long next = 0;
      boolean more = false;
      for (var it = pending.values().iterator(); it.hasNext(); ) {
        Pending p = it.next();
        if (p.timeout() == null) {
          continue;
        }
        if (p.at() - now <= 0) {
          expired.add(p);
          it.remove();
        } else if (!more || p.at() - next < 0) {
          next = p.at();
          more = true;
        }
      }
      if (!expired.isEmpty()) {
        if (pending.isEmpty()) {
          notifyAll();
        }
      } else if (more) {
        watchAt(next);
      }
    }
    if (expired.isEmpty()) {
      return;
    }
    String why = null;
    for (Pending p : expired) {
      String seconds = p.timeout().toMillis() / 1000.0 + " s";
      if (why == null) {
        why = endpoint + " answered no write on the shared-memory session within its deadline (" + p.what()
            + " waited " + seconds + "): the server looks hung, so the session was ended";
      }
      p.reply()
          .completeExceptionally(
              new DeadlineExceededError(
                  "no reply from " + endpoint + " to the " + p.what() + " within " + seconds + " on the"
                      + " shared-memory session: it may or may not have been applied; the session was ended and"
                      + " the next write opens a new one"));
    }
    session.end(why); // the others fail with UnavailableError
  }
}
