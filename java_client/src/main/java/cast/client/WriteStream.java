package cast.client;

import cast.v1.WriteError;
import cast.v1.WriteReply;
import cast.v1.WriteRequest;
import java.time.Duration;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.CompletionException;
import java.util.concurrent.ExecutionException;
import java.util.concurrent.Executor;
import java.util.concurrent.LinkedBlockingQueue;
import java.util.concurrent.RejectedExecutionException;
import java.util.concurrent.ThreadPoolExecutor;
import java.util.concurrent.TimeUnit;

/**
 * A component's writes and locks on one {@code WorkingMemory.Write} stream to one server
 * (docs/client-protocol.md, "Write stream"): each request gets the next id of its call and
 * exactly one reply with that id, so a write costs a message each way instead of a whole
 * unary call, and many may be in flight ({@link #submitWrite} returns a future). Requests are
 * sent in call order on one call, which the server applies in arrival order, so a component's
 * writes keep their order. The twin of python/cast/client/write_stream.py and
 * cpp_client/src/write_stream.cc.
 *
 * <p>The call is opened on the first write and again after it broke; its metadata carries the
 * token of the moment. Before each send the token is checked (a {@code stat} of the token file
 * at most once a second, {@link Credentials}); when the orchestrator has renewed it, a new call
 * opens with the new token once the old call's outstanding requests are answered (so no write
 * overtakes an earlier one). A request refused as UNAUTHENTICATED (alone, or with its whole
 * call when the server refused the call's token as it opened) is sent once more when the token
 * file holds another token (a refused request changed nothing). A call that breaks otherwise
 * fails its outstanding requests with UnavailableError, as a broken unary call, and the next
 * write opens a new one.
 *
 * <p>One thread at a time sends: a synchronous caller when nobody else is (no thread hop on the
 * way out), for asynchronous writes the component's pump thread. Requests that queue up while
 * a message is sent, or while gRPC takes nothing ({@code isReady} false), go together in the
 * next message (of about {@link #MESSAGE_BYTES}), so many writes in flight cost the server few
 * messages; a sender waits (up to the call timeout) while {@link #OUTBOX_BYTES} are queued: a
 * component that writes faster than the server reads is held back instead of buffering
 * without bound.
 *
 * <p>On the server's host, while the component has a shared-memory session with that server
 * ({@link SharedLink}), every request goes on the session's Unix socket instead, in a WRITES frame
 * that the sending thread writes itself, and its reply comes in a REPLIES frame ({@link
 * SessionWrites}; docs/client-protocol.md, "Writes on the session's socket"): the same messages
 * and rules, without gRPC's threads and hand-offs on either side. All or nothing: the server has
 * no order between two transports, so a request goes on the socket only once what the gRPC call
 * has outstanding was answered, and on the gRPC call again only once the session ended (which
 * failed what it had outstanding). The session's identity is the token of its HELLO: when the
 * token was renewed, the session gives way to a new one once its outstanding requests were
 * answered. {@code CAST_SHARED_MEMORY=off}, or a server elsewhere, leaves everything on the gRPC
 * call. A component's single-entry reads go on the session's socket too, after its writes, when
 * the server answers them there ({@link #read}): a frame each way costs a fraction of a unary call.
 */
final class WriteStream {
  /**
   * How long a token change waits for the old call's (or session's) outstanding replies before
   * opening the new one; and a switch from the gRPC call to the session's socket, for the call's.
   */
  static final Duration DRAIN = Duration.ofSeconds(30);
  /** Requests that queued up go in messages of at most about this many bytes (a larger request alone). */
  static final int MESSAGE_BYTES = 1 << 20;
  /** Senders wait while this many bytes of requests are queued and not yet taken by gRPC. */
  static final long OUTBOX_BYTES = 16L << 20;

  private final GrpcServer server;
  private final Credentials credentials;
  private final Duration callTimeout;
  private final Executor pump; // sends what asynchronous writes queued
  private final Object sendLock = new Object(); // one sender at a time: ids and the order of requests agree
  private WriteCall call; // guarded by sendLock
  private volatile boolean closed;

  /**
   * The Write stream to {@code server}; {@code callTimeout} bounds the wait for room to send;
   * {@code pump} sends the requests of asynchronous writes.
   */
  WriteStream(GrpcServer server, Credentials credentials, Duration callTimeout, Executor pump) {
    this.server = server;
    this.credentials = credentials;
    this.callTimeout = callTimeout;
    this.pump = pump;
  }

  /**
   * One thread of a component's, started on demand and gone after 30 s idle, running tasks in
   * order: where the futures of {@link #submitWrite} complete (off the gRPC threads, in reply
   * order), and where asynchronous writes are sent from. Once shut down, what is left runs in
   * the thread that hands it over.
   */
  static final class Worker implements Executor {
    private final ThreadPoolExecutor pool;

    Worker(String threadName) {
      pool =
          new ThreadPoolExecutor(
              0,
              1,
              30,
              TimeUnit.SECONDS,
              new LinkedBlockingQueue<>(),
              r -> {
                Thread t = new Thread(r, threadName);
                t.setDaemon(true);
                return t;
              });
    }

    @Override
    public void execute(Runnable task) {
      try {
        pool.execute(task);
      } catch (RejectedExecutionException e) {
        task.run();
      }
    }

    /** Run what is queued, take nothing new. */
    void shutdown() {
      pool.shutdown();
    }
  }

  // ----------------------------------------------------------- sending

  /**
   * Send {@code request} (its id is set here) after every earlier one; the future of its reply.
   * On the session's socket the caller writes its frame itself. On the gRPC call, a synchronous
   * caller ({@code async} false) sends it itself when nobody else is sending; an asynchronous one
   * leaves it to the pump and returns at once, so the requests it queues go together.
   */
  CompletableFuture<WriteReply> submit(WriteRequest.Builder request, boolean async, Duration deadline) {
    // Refused here, in front of both transports: a message over the limit would end the gRPC
    // call, or the session (a WRITES frame has the same bound), failing every write in flight.
    long size = request.build().getSerializedSize();
    if (size > GrpcServer.MAX_MESSAGE_BYTES) {
      throw new InvalidArgumentError(
          "a write of " + size + " bytes is over the gRPC message limit of " + GrpcServer.MAX_MESSAGE_BYTES
              + " bytes (64 MiB) and was not sent; the server keeps values of at most limits.max_value_bytes"
              + " (8 MiB by default): store large data elsewhere and keep a reference");
    }
    String token = credentials.token();
    SharedLink link = server.shared;
    Duration within = deadline != null ? deadline : callTimeout;
    // Opened on the way if there is none (within the request's time), and a renewed token's new
    // one opened after the old one's replies, outside the lock: the other writers need not wait
    // for a DescribeSystem and a handshake.
    SharedSession session = link == null ? null : link.writerSession(within);
    synchronized (sendLock) {
      if (session != null) {
        CompletableFuture<WriteReply> reply = onSession(link, session, request, deadline, within, async);
        if (reply != null) {
          return reply;
        }
      }
      for (int attempt = 0; ; attempt++) {
        if (closed) {
          throw closedError();
        }
        WriteCall c = call;
        if (c == null || c.isBroken() || !c.token.equals(token)) {
          c = open(c, token);
        }
        CompletableFuture<WriteReply> reply = c.send(request, size, async, deadline);
        if (reply != null) {
          return reply;
        }
        if (attempt > 0) { // a new call that broke at once: the server is not there
          throw c.brokenError();
        }
      }
    }
  }

  /**
   * Send {@code request} on the session's socket (holding sendLock); null when no session is left
   * to take it (it ended just now, and no new one opens): the gRPC call takes it then.
   */
  private CompletableFuture<WriteReply> onSession(
      SharedLink link,
      SharedSession session,
      WriteRequest.Builder request,
      Duration deadline,
      Duration within,
      boolean async) {
    for (int attempt = 0; session != null && attempt < 2; attempt++) {
      if (closed) {
        throw closedError();
      }
      drainOthers(link, session);
      CompletableFuture<WriteReply> reply = session.writes().send(request, deadline, !async);
      if (reply != null) {
        return reply;
      }
      session = link.session(within); // it ended just now: a new one, or none (then gRPC)
    }
    return null;
  }

  /**
   * Wait (holding sendLock) until what the gRPC call, and a renewed token's session still
   * answering, have outstanding was answered, so that a request on {@code session}'s socket
   * overtakes none of them: the server has no order between two transports. At once when they
   * have nothing outstanding.
   */
  private void drainOthers(SharedLink link, SharedSession session) {
    WriteCall c = call;
    if (c != null && !c.isBroken()) {
      c.drain(DRAIN);
    }
    SharedSession old = link == null ? null : link.retiring(); // another thread is waiting for its replies
    if (old != null && old != session) {
      old.writes().drain(DRAIN);
    }
  }

  /**
   * Send a read (a get) on {@code session}'s socket after every request sent before it, and wait
   * up to {@code wait} for its reply; null, with nothing sent, when the session has ended (the
   * caller then makes the unary call). The read's lent value belongs to the session whose socket
   * carries it (its {@code read_call} is one of that session's), so it goes on that socket or not
   * at all, never on the gRPC call. The waiting thread reads its reply itself as a waiting writer
   * does (a get never waits on the server); the reply's error is thrown as the unary call's would
   * be. The twin of {@code WriteStream.read} in python/cast/client/write_stream.py.
   */
  WriteReply read(SharedSession session, WriteRequest.Builder request, Duration wait) {
    SessionWrites.Reply reply;
    synchronized (sendLock) {
      if (closed) {
        throw closedError();
      }
      drainOthers(server.shared, session); // the read sees the writes sent before it by gRPC too
      reply = session.writes().send(request, wait, true);
    }
    return reply == null ? null : checked(await(reply));
  }

  /** What a write gets once the transport is closing. */
  private UnavailableError closedError() {
    return new UnavailableError(
        "the connection to " + server.endpoint + " is closed: no more writes (the component is stopping)");
  }

  /** Open a new call with {@code token}, after the old one (if it still works) answered everything. */
  private WriteCall open(WriteCall old, String token) {
    if (old != null && !old.isBroken()) {
      old.drain(DRAIN); // the new token's call must not overtake the old one's writes
      old.halfClose();
    }
    call = new WriteCall(server, token, callTimeout, pump);
    return call;
  }

  /**
   * Send {@code request} and wait up to {@code wait} (null: as long as it takes) for its
   * result; a refusal thrown as the named error the unary call would have thrown,
   * DeadlineExceededError past {@code wait} (the call it went on then ends: {@link WriteCall}).
   */
  WriteReply call(WriteRequest.Builder request, Duration wait) {
    WriteReply reply;
    try {
      reply = await(submit(request, false, wait));
    } catch (UnauthenticatedError refused) { // the whole call was refused: its token, when it opened
      if (!credentials.refresh()) {
        throw refused;
      }
      return checked(await(submit(request, false, wait)));
    }
    if (reply.hasError() && reply.getError().getCode().equals("UNAUTHENTICATED") && credentials.refresh()) {
      reply = await(submit(request, false, wait)); // renewed in its file: the new token goes on a new call
    }
    return checked(reply);
  }

  /**
   * Send an add, overwrite or delete without waiting: the future of its result, completed on
   * {@code results} (in reply order), its failure the named error.
   */
  CompletableFuture<WriteResult> submitWrite(WriteRequest.Builder request, Executor results) {
    return submitWrite(request, results, callTimeout);
  }

  /** {@link #submitWrite(WriteRequest.Builder, Executor)}, failing past {@code deadline} instead of the call timeout. */
  CompletableFuture<WriteResult> submitWrite(WriteRequest.Builder request, Executor results, Duration deadline) {
    CompletableFuture<WriteResult> out = new CompletableFuture<>();
    CompletableFuture<WriteReply> sent;
    try {
      sent = submit(request, true, deadline);
    } catch (CastError e) {
      out.completeExceptionally(e);
      return out;
    }
    // Not completed on the gRPC thread that read the reply: a continuation that writes
    // synchronously there would wait for a reply only that thread can deliver.
    sent.whenCompleteAsync(
        (reply, failure) -> {
          try {
            if (failure != null) {
              throw Errors.fromThrowable(failure instanceof CompletionException ? failure.getCause() : failure);
            }
            out.complete(Conversions.result(checked(reply).getWrite()));
          } catch (CastError e) {
            out.completeExceptionally(e);
          }
        },
        results);
    return out;
  }

  /** The reply if it carries a result; the error the unary call would have thrown otherwise. */
  static WriteReply checked(WriteReply reply) {
    if (reply.hasError()) {
      WriteError e = reply.getError();
      throw Errors.forCode(e.getCode(), e.getMessage(), e.getErrorClass().isEmpty() ? null : e.getErrorClass());
    }
    return reply;
  }

  /** The reply; a request with a deadline is failed by its call when the deadline passes. */
  private static WriteReply await(CompletableFuture<WriteReply> reply) {
    if (reply instanceof SessionWrites.Reply r) {
      r.writes.await(r); // this thread reads its reply on the session's socket when no other does
    }
    try {
      return reply.get();
    } catch (ExecutionException e) {
      throw Errors.fromThrowable(e.getCause());
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
      throw new CastError(
          "CANCELLED", "interrupted while waiting for the reply to a write: it may or may not have been applied");
    }
  }

  /**
   * Stop sending; wait up to {@code timeout} for outstanding replies (on the session's socket,
   * then on the call: they may be asynchronous results), then end the call. The session itself
   * is ended by the transport afterwards.
   */
  void close(Duration timeout) {
    WriteCall c;
    synchronized (sendLock) {
      closed = true;
      c = call;
      call = null;
    }
    SharedLink link = server.shared;
    SharedSession session = link == null ? null : link.current();
    if (session != null) {
      session.writes().drain(timeout);
    }
    if (c == null) {
      return;
    }
    c.drain(timeout);
    c.halfClose();
    if (!c.awaitEnd(timeout)) {
      c.cancel();
    }
  }
}
