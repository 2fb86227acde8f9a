package cast.client;

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
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.Executor;
import java.util.concurrent.ScheduledFuture;
import java.util.concurrent.ScheduledThreadPoolExecutor;
import java.util.concurrent.TimeUnit;
import java.util.logging.Logger;

/**
 * One open {@code WorkingMemory.Write} call of a {@link WriteStream}: the requests it has not
 * sent yet, its outstanding requests by id, and how it ended. Its monitor guards all of that;
 * senders, the reply reader and gRPC's onReady take it briefly, and messages are handed to
 * gRPC outside it by one thread at a time (the one that set {@code sending}). The twin of
 * {@code _Call} in python/cast/client/write_stream.py.
 *
 * <p>A request sent with a deadline fails with DeadlineExceededError when it passes unanswered,
 * and the call is then ended (its other requests fail with UnavailableError; the next write opens
 * a new call): a server that answers nothing in that time is hung, or the path to it is, and
 * keepalive alone would notice only when the connection's ping goes unanswered.
 */
final class WriteCall implements ClientResponseObserver<WriteRequests, WriteReplies> {
  private static final Logger LOG = Logger.getLogger("cast.client");
  /**
   * Where the deadlines of every call of the process are timed, and those of the writes on
   * shared-memory sessions' sockets ({@link SessionWrites}): one daemon thread.
   */
  static final ScheduledThreadPoolExecutor DEADLINES = deadlineTimer();

  private final GrpcServer server;
  final String token; // the token its metadata carried
  private final Duration callTimeout;
  private final Executor pump;
  // All guarded by this (the call's monitor; senders, the reply reader and onReady take it briefly).
  private final ArrayDeque<WriteRequest> outbox = new ArrayDeque<>();
  private long outboxBytes;
  private final Map<Long, CompletableFuture<WriteReply>> pending = new HashMap<>();
  private long lastId;
  private boolean sending; // a thread is in sendQueued: it takes along whatever is queued
  private final Map<Long, ScheduledFuture<?>> timers = new HashMap<>(); // outstanding ids with a deadline
  private boolean broken;
  private Status endStatus;
  private ClientCallStreamObserver<WriteRequests> requests;
  private final CountDownLatch ended = new CountDownLatch(1);

  /**
   * Opens the call to {@code server} with the token of the moment, {@code token}; a sender
   * waits up to {@code callTimeout} for room; {@code pump} sends for asynchronous writes.
   */
  WriteCall(GrpcServer server, String token, Duration callTimeout, Executor pump) {
    this.server = server;
    this.token = token;
    this.callTimeout = callTimeout;
    this.pump = pump;
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

  private static ScheduledThreadPoolExecutor deadlineTimer() {
    ScheduledThreadPoolExecutor timer =
        new ScheduledThreadPoolExecutor(
            1,
            r -> {
              Thread t = new Thread(r, "cast-write-deadlines");
              t.setDaemon(true);
              return t;
            });
    timer.setRemoveOnCancelPolicy(true); // answered requests' timers go at once, not after their delay
    return timer;
  }

  /**
   * Queue {@code request} ({@code size} bytes) under the next id; the future of its reply, or
   * null when the call has broken. Waits while the outbox is full. When nobody is sending, a
   * synchronous caller sends what is queued itself; an asynchronous one hands that to the pump.
   * Past {@code deadline} (null: none) the future fails with DeadlineExceededError and the call
   * ends.
   */
  CompletableFuture<WriteReply> send(WriteRequest.Builder request, long size, boolean async, Duration deadline) {
    CompletableFuture<WriteReply> reply = new CompletableFuture<>();
    boolean sendHere;
    synchronized (this) {
      awaitRoom();
      if (broken) {
        return null;
      }
      long id = ++lastId;
      pending.put(id, reply);
      if (deadline != null) {
        String what = describe(request);
        timers.put(
            id, DEADLINES.schedule(() -> expire(id, deadline, what), deadline.toNanos(), TimeUnit.NANOSECONDS));
      }
      outbox.add(request.setId(id).build());
      outboxBytes += size;
      if (sending) {
        return reply; // whoever sends takes it along
      }
      sending = true;
      sendHere = !async;
    }
    if (sendHere) {
      sendQueued();
    } else {
      pump.execute(this::sendQueued);
    }
    return reply;
  }

  /** Wait while the outbox is full (holding this), up to the call timeout. */
  private void awaitRoom() {
    long deadline = System.nanoTime() + callTimeout.toNanos();
    while (!broken && outboxBytes >= WriteStream.OUTBOX_BYTES) {
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
  }

  /**
   * Hand what is queued to gRPC, in messages of about {@link WriteStream#MESSAGE_BYTES}, while it takes
   * them; what queues up meanwhile goes in the next message. Only the thread that set
   * {@code sending} runs this, so messages go out one at a time and in order; it stops when
   * the outbox is empty or gRPC is not ready (onReady starts it again).
   */
  private void sendQueued() {
    while (true) {
      WriteRequests.Builder message = WriteRequests.newBuilder();
      ClientCallStreamObserver<WriteRequests> stream;
      synchronized (this) {
        stream = requests;
        if (broken || outbox.isEmpty() || stream == null || !stream.isReady()) {
          sending = false;
          notifyAll(); // halfClose waits for the sender to finish
          return;
        }
        long bytes = 0;
        do {
          long size = outbox.peekFirst().getSerializedSize();
          if (message.getRequestsCount() > 0 && bytes + size > WriteStream.MESSAGE_BYTES) {
            break;
          }
          message.addRequests(outbox.pollFirst());
          bytes += size;
        } while (!outbox.isEmpty());
        outboxBytes -= bytes;
        notifyAll(); // room for senders waiting
      }
      try {
        stream.onNext(message.build());
      } catch (RuntimeException e) { // the call ended under us: its end fails what is outstanding
        LOG.fine("write requests not sent, the call ended: " + e.getMessage());
        synchronized (this) {
          outbox.clear();
          outboxBytes = 0;
          sending = false;
          notifyAll();
        }
        return;
      }
    }
  }

  /** gRPC takes messages again: send what waited, unless someone is sending. */
  private void ready() {
    synchronized (this) {
      if (sending || outbox.isEmpty()) {
        return;
      }
      sending = true;
    }
    sendQueued();
  }

  @Override
  public void onNext(WriteReplies replies) {
    List<CompletableFuture<WriteReply>> answered = new ArrayList<>(replies.getRepliesCount());
    synchronized (this) {
      for (WriteReply reply : replies.getRepliesList()) {
        answered.add(pending.remove(reply.getId()));
        ScheduledFuture<?> timer = timers.remove(reply.getId());
        if (timer != null) {
          timer.cancel(false);
        }
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
      timers.values().forEach(timer -> timer.cancel(false));
      timers.clear();
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
   * Request {@code id} passed its deadline unanswered: it fails with DeadlineExceededError, and
   * the call ends (the server looks hung), failing the others.
   */
  private void expire(long id, Duration waited, String what) {
    CompletableFuture<WriteReply> reply;
    ClientCallStreamObserver<WriteRequests> stream;
    String seconds = waited.toMillis() / 1000.0 + " s";
    synchronized (this) {
      timers.remove(id);
      reply = pending.remove(id);
      if (reply == null || broken) {
        return; // answered meanwhile, or the call ended and failed it
      }
      stream = requests;
    }
    reply.completeExceptionally(
        new DeadlineExceededError(
            "no reply from " + server.endpoint + " to the " + what + " within " + seconds
                + ": it may or may not have been applied; the write stream was ended and the next write opens a"
                + " new one"));
    stream.cancel(
        server.endpoint + " answered no request within its deadline (" + what + " waited " + seconds
            + "): the server looks hung, so the stream was ended",
        null);
  }

  /** How an error names a request: "add of 'x'", "lock of 'x'", "batch of 3 writes". */
  static String describe(WriteRequest.Builder request) {
    return switch (request.getOperationCase()) {
      case ADD -> "add of '" + request.getAdd().getAddress().getId() + "'";
      case OVERWRITE -> "overwrite of '" + request.getOverwrite().getAddress().getId() + "'";
      case DELETE -> "delete of '" + request.getDelete().getAddress().getId() + "'";
      case BATCH -> "batch of " + request.getBatch().getOperationsCount() + " writes";
      case LOCK -> "lock of '" + request.getLock().getAddress().getId() + "'";
      case UNLOCK -> "unlock of '" + request.getUnlock().getAddress().getId() + "'";
      case GET -> "get of '" + request.getGet().getAddress().getId() + "'";
      default -> "request";
    };
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
    Monitors.waitUntil(this, () -> pending.isEmpty() || broken, timeout);
  }

  /** Half-close, once what is queued was handed to gRPC: the server answers what it has and ends the call. */
  synchronized void halfClose() {
    long deadline = System.nanoTime() + TimeUnit.SECONDS.toNanos(2);
    try {
      while (sending && !broken && System.nanoTime() < deadline) { // never beside an onNext
        TimeUnit.MILLISECONDS.timedWait(this, 50);
      }
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
    }
    if (broken || requests == null || sending) {
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
