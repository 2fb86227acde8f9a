package cast.client;

import cast.v1.WriteError;
import cast.v1.WriteReplies;
import cast.v1.WriteReply;
import cast.v1.WriteRequest;
import cast.v1.WriteRequests;
import io.grpc.Status;
import io.grpc.stub.ClientCallStreamObserver;
import io.grpc.stub.ClientResponseObserver;
import java.time.Duration;
import java.util.ArrayDeque;
import java.util.ArrayList;
import java.util.HashMap;
import java.util.List;
import java.util.Map;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.CompletionException;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.ExecutionException;
import java.util.concurrent.Executor;
import java.util.concurrent.LinkedBlockingQueue;
import java.util.concurrent.RejectedExecutionException;
import java.util.concurrent.ThreadPoolExecutor;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.TimeoutException;
import java.util.logging.Logger;

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
 * <p>Requests go to gRPC at once while it takes them ({@code isReady}); otherwise they queue up
 * and go together, in messages of about {@link #MESSAGE_BYTES}, when it is ready again, and a
 * sender waits (up to the call timeout) while {@link #OUTBOX_BYTES} are queued: a component
 * that writes faster than the server reads is held back instead of buffering without bound.
 */
final class WriteStream {
  private static final Logger LOG = Logger.getLogger("cast.client");
  /** How long a token change waits for the old call's outstanding replies before opening the new call. */
  static final Duration DRAIN = Duration.ofSeconds(30);
  /** Requests that queued up go in messages of at most about this many bytes (a larger request alone). */
  static final int MESSAGE_BYTES = 1 << 20;
  /** Senders wait while this many bytes of requests are queued and not yet taken by gRPC. */
  static final long OUTBOX_BYTES = 16L << 20;

  private final GrpcServer server;
  private final Credentials credentials;
  private final Duration callTimeout;
  private final Object sendLock = new Object(); // one sender at a time: ids and the order of requests agree
  private Call call; // guarded by sendLock
  private volatile boolean closed;

  /** The Write stream to {@code server}; {@code callTimeout} bounds the wait for room to send. */
  WriteStream(GrpcServer server, Credentials credentials, Duration callTimeout) {
    this.server = server;
    this.credentials = credentials;
    this.callTimeout = callTimeout;
  }

  /**
   * Where the futures of {@link #submitWrite} complete: one thread per component, in reply
   * order, off the gRPC threads; started on demand and gone after 30 s idle. Once shut down,
   * what is left runs in the thread that completes it.
   */
  static final class Results implements Executor {
    private final ThreadPoolExecutor pool;

    Results(String name) {
      pool =
          new ThreadPoolExecutor(
              0,
              1,
              30,
              TimeUnit.SECONDS,
              new LinkedBlockingQueue<>(),
              r -> {
                Thread t = new Thread(r, "cast-write-results-" + name);
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

  /** Send {@code request} (its id is set here) after every earlier one; the future of its reply. */
  CompletableFuture<WriteReply> submit(WriteRequest.Builder request) {
    long size = request.build().getSerializedSize();
    if (size > GrpcServer.MAX_MESSAGE_BYTES) {
      throw new InvalidArgumentError(
          "a write of " + size + " bytes is over the gRPC message limit of " + GrpcServer.MAX_MESSAGE_BYTES
              + " bytes (64 MiB) and was not sent; the server keeps values of at most limits.max_value_bytes"
              + " (8 MiB by default): store large data elsewhere and keep a reference");
    }
    String token = credentials.token();
    synchronized (sendLock) {
      for (int attempt = 0; ; attempt++) {
        if (closed) {
          throw new UnavailableError(
              "the connection to " + server.endpoint + " is closed: no more writes (the component is stopping)");
        }
        Call c = call;
        if (c == null || c.isBroken() || !c.token.equals(token)) {
          c = open(c, token);
        }
        CompletableFuture<WriteReply> reply = c.send(request, size);
        if (reply != null) {
          return reply;
        }
        if (attempt > 0) { // a new call that broke at once: the server is not there
          throw c.brokenError();
        }
      }
    }
  }

  /** Open a new call with {@code token}, after the old one (if it still works) answered everything. */
  private Call open(Call old, String token) {
    if (old != null && !old.isBroken()) {
      old.drain(DRAIN); // the new token's call must not overtake the old one's writes
      old.halfClose();
    }
    call = new Call(token);
    return call;
  }

  /**
   * Send {@code request} and wait up to {@code wait} (null: as long as it takes) for its
   * result; a refusal thrown as the named error the unary call would have thrown.
   */
  WriteReply call(WriteRequest.Builder request, Duration wait) {
    WriteReply reply;
    try {
      reply = await(submit(request), wait);
    } catch (UnauthenticatedError refused) { // the whole call was refused: its token, when it opened
      if (!credentials.refresh()) {
        throw refused;
      }
      return checked(await(submit(request), wait));
    }
    if (reply.hasError() && reply.getError().getCode().equals("UNAUTHENTICATED") && credentials.refresh()) {
      reply = await(submit(request), wait); // renewed in its file: the new token goes on a new call
    }
    return checked(reply);
  }

  /**
   * Send an add, overwrite or delete without waiting: the future of its result, completed on
   * {@code results} (in reply order), its failure the named error.
   */
  CompletableFuture<WriteResult> submitWrite(WriteRequest.Builder request, Executor results) {
    CompletableFuture<WriteResult> out = new CompletableFuture<>();
    CompletableFuture<WriteReply> sent;
    try {
      sent = submit(request);
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

  private WriteReply await(CompletableFuture<WriteReply> reply, Duration wait) {
    try {
      return wait == null ? reply.get() : reply.get(wait.toNanos(), TimeUnit.NANOSECONDS);
    } catch (TimeoutException e) {
      throw new DeadlineExceededError(
          "no reply from " + server.endpoint + " to a write within " + wait.toMillis() / 1000.0
              + " s: it may or may not have been applied");
    } catch (ExecutionException e) {
      throw Errors.fromThrowable(e.getCause());
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
      throw new CastError(
          "CANCELLED", "interrupted while waiting for the reply to a write: it may or may not have been applied");
    }
  }

  /** Stop sending; wait up to {@code timeout} for outstanding replies, then end the call. */
  void close(Duration timeout) {
    Call c;
    synchronized (sendLock) {
      closed = true;
      c = call;
      call = null;
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

  // ------------------------------------------------------------- one call

  /** One open Write call: what it has not sent yet, its outstanding requests, and how it ended. */
  private final class Call implements ClientResponseObserver<WriteRequests, WriteReplies> {
    final String token; // the token its metadata carried
    // All guarded by this (the call's monitor; senders, the reply reader and onReady take it briefly).
    private final ArrayDeque<WriteRequest> outbox = new ArrayDeque<>();
    private long outboxBytes;
    private final Map<Long, CompletableFuture<WriteReply>> pending = new HashMap<>();
    private long lastId;
    private boolean broken;
    private Status endStatus;
    private ClientCallStreamObserver<WriteRequests> requests;
    private final CountDownLatch ended = new CountDownLatch(1);

    Call(String token) {
      this.token = token;
      server.wmAsync.write(this); // beforeStart sets `requests`; requests go out once gRPC is ready
    }

    @Override
    public void beforeStart(ClientCallStreamObserver<WriteRequests> stream) {
      synchronized (this) {
        requests = stream;
      }
      stream.setOnReadyHandler(this::ready);
    }

    synchronized boolean isBroken() {
      return broken;
    }

    /**
     * Queue {@code request} ({@code size} bytes) under the next id and send what gRPC takes;
     * the future of its reply, or null when the call has broken. Waits while the outbox is full.
     */
    synchronized CompletableFuture<WriteReply> send(WriteRequest.Builder request, long size) {
      long deadline = System.nanoTime() + callTimeout.toNanos();
      while (!broken && outboxBytes >= OUTBOX_BYTES) {
        long left = deadline - System.nanoTime();
        if (left <= 0) {
          throw new DeadlineExceededError(
              "the write stream to " + server.endpoint + " took nothing for " + callTimeout.toMillis() / 1000.0
                  + " s (" + outboxBytes + " bytes wait to be sent): this write was not sent");
        }
        try {
          TimeUnit.NANOSECONDS.timedWait(this, left);
        } catch (InterruptedException e) {
          Thread.currentThread().interrupt();
          throw new CastError("CANCELLED", "interrupted while waiting to send a write: it was not sent");
        }
      }
      if (broken) {
        return null;
      }
      long id = ++lastId;
      CompletableFuture<WriteReply> reply = new CompletableFuture<>();
      pending.put(id, reply);
      outbox.add(request.setId(id).build());
      outboxBytes += size;
      flush();
      return reply;
    }

    /** Hand queued requests to gRPC while it takes them (holding this). */
    private void flush() {
      while (!outbox.isEmpty() && requests != null && requests.isReady()) {
        WriteRequests.Builder message = WriteRequests.newBuilder();
        long bytes = 0;
        do {
          long size = outbox.peekFirst().getSerializedSize();
          if (message.getRequestsCount() > 0 && bytes + size > MESSAGE_BYTES) {
            break;
          }
          message.addRequests(outbox.pollFirst());
          bytes += size;
        } while (!outbox.isEmpty());
        outboxBytes -= bytes;
        try {
          requests.onNext(message.build());
        } catch (RuntimeException e) { // the call ended under us: its end fails what is outstanding
          LOG.fine("write requests not sent, the call ended: " + e.getMessage());
          outbox.clear();
          outboxBytes = 0;
        }
      }
      notifyAll(); // senders waiting for room, drains
    }

    private synchronized void ready() {
      flush();
    }

    @Override
    public void onNext(WriteReplies replies) {
      List<CompletableFuture<WriteReply>> answered = new ArrayList<>(replies.getRepliesCount());
      synchronized (this) {
        for (WriteReply reply : replies.getRepliesList()) {
          answered.add(pending.remove(reply.getId()));
        }
        if (pending.isEmpty()) {
          notifyAll();
        }
      }
      for (int i = 0; i < answered.size(); i++) {
        if (answered.get(i) != null) {
          answered.get(i).complete(replies.getReplies(i));
        }
      }
    }

    @Override
    public void onError(Throwable t) {
      end(Status.fromThrowable(t));
    }

    @Override
    public void onCompleted() {
      end(Status.UNAVAILABLE.withDescription("the server ended it"));
    }

    /** The call ended: every outstanding request fails (it may or may not have been applied). */
    private void end(Status status) {
      List<CompletableFuture<WriteReply>> left;
      synchronized (this) {
        broken = true;
        endStatus = status;
        left = new ArrayList<>(pending.values());
        pending.clear();
        outbox.clear();
        outboxBytes = 0;
        notifyAll();
      }
      ended.countDown();
      if (status.getCode() == Status.Code.UNAVAILABLE) {
        server.channel.resetConnectBackoff(); // the next write tries the server at once
      }
      for (CompletableFuture<WriteReply> reply : left) {
        reply.completeExceptionally(brokenError());
      }
    }

    /**
     * What an outstanding request of a broken call fails with: UnavailableError, or the
     * server's UnauthenticatedError when it refused the call's token as it opened (then
     * nothing was applied).
     */
    synchronized CastError brokenError() {
      Status s = endStatus == null ? Status.UNAVAILABLE : endStatus;
      if (s.getCode() == Status.Code.UNAUTHENTICATED) {
        return Errors.fromStatus(s);
      }
      return new UnavailableError(
          "the write stream to " + server.endpoint + " broke (" + s.getCode()
              + (s.getDescription() == null ? "" : ": " + s.getDescription())
              + "): this write may or may not have been applied; the client reconnects by itself, retry the"
              + " call later");
    }

    /** Wait until every outstanding request is answered, or {@code timeout}. */
    synchronized void drain(Duration timeout) {
      long deadline = System.nanoTime() + timeout.toNanos();
      try {
        while (!pending.isEmpty() && !broken) {
          long left = deadline - System.nanoTime();
          if (left <= 0) {
            return;
          }
          TimeUnit.NANOSECONDS.timedWait(this, left);
        }
      } catch (InterruptedException e) {
        Thread.currentThread().interrupt();
      }
    }

    /** Half-close: the server answers what it has and ends the call. */
    synchronized void halfClose() {
      if (broken || requests == null) {
        return;
      }
      try {
        requests.onCompleted();
      } catch (RuntimeException e) {
        LOG.fine("write call already ended: " + e.getMessage());
      }
    }

    boolean awaitEnd(Duration timeout) {
      try {
        return ended.await(timeout.toNanos(), TimeUnit.NANOSECONDS);
      } catch (InterruptedException e) {
        Thread.currentThread().interrupt();
        return false;
      }
    }

    void cancel() {
      ClientCallStreamObserver<WriteRequests> r;
      synchronized (this) {
        r = requests;
      }
      if (r != null) {
        r.cancel("component closing", null);
      }
    }
  }
}
