package cast.client;

import cast.v1.AwaitRunRequest;
import cast.v1.HeartbeatRequest;
import cast.v1.HeartbeatResponse;
import cast.v1.RegisterRequest;
import cast.v1.RegisterResponse;
import io.grpc.stub.StreamObserver;
import java.lang.management.ManagementFactory;
import java.net.InetAddress;
import java.time.Duration;
import java.util.concurrent.RejectedExecutionException;
import java.util.concurrent.ScheduledFuture;
import java.util.concurrent.TimeUnit;
import java.util.function.Supplier;
import java.util.logging.Level;
import java.util.logging.Logger;

/**
 * A component's session with one server (docs/client-protocol.md, start-up step 3
 * and "Reconnection"): {@code Directory.Register}, then a Heartbeat stream that sends
 * the component's state every third of the lease and whenever it changes. The
 * session, and with it the component's locks and tasks, ends when that stream ends;
 * a lost session is registered again with backoff (a new session: the old one's
 * locks and tasks are gone). The answer to Register says who the component is, as
 * the server verified it from the token. {@link #awaitRun} waits at the start barrier
 * (start-up, after start()). The twin of python/cast/client/session.py and
 * cpp_client/src/session.cc.
 */
final class Session {
  private static final Logger LOG = Logger.getLogger("cast.client");

  private final GrpcTransport transport;
  private final GrpcServer server;
  private final String language;
  private final String kind;
  private final Supplier<ComponentState> state;
  private final Backoff backoff = new Backoff();
  private volatile String sessionId = "";
  private volatile StreamObserver<HeartbeatRequest> heartbeat; // sends guarded by the observer itself
  private volatile ScheduledFuture<?> beat;
  private volatile Runnable beatNow;

  Session(
      GrpcTransport transport,
      GrpcServer server,
      String language,
      String kind,
      Supplier<ComponentState> state) {
    this.transport = transport;
    this.server = server;
    this.language = language;
    this.kind = kind;
    this.state = state;
  }

  /** Register and start the heartbeats; returns the identity the server verified from the token. */
  Identity open() {
    RegisterResponse resp = register();
    openHeartbeat(interval(resp));
    return Conversions.identity(resp);
  }

  /** The id of the current session ("" before the first registration). */
  String sessionId() {
    return sessionId;
  }

  private RegisterResponse register() {
    var req =
        RegisterRequest.newBuilder()
            .setLanguage(language)
            .setKind(kind)
            .setPid(ProcessHandle.current().pid())
            .setHost(hostName())
            .setLibraryVersion(Version.library())
            .build();
    RegisterResponse resp = transport.call(server, server.dir, s -> s.register(req));
    sessionId = resp.getSessionId();
    transport.countSession();
    return resp;
  }

  /** The heartbeat interval in milliseconds: a third of the lease. */
  private static long interval(RegisterResponse resp) {
    return Math.max(50, resp.getLeaseMs() / 3);
  }

  /** One heartbeat stream of one session; sends are serialised on the object itself. */
  private final class Heartbeat implements StreamObserver<HeartbeatResponse> {
    StreamObserver<HeartbeatRequest> requests;

    @Override
    public void onNext(HeartbeatResponse value) {
      backoff.reset();
    }

    // synchronized: waits until openHeartbeat has recorded the stream (a call may fail at once).
    @Override
    public synchronized void onError(Throwable t) {
      lost(requests, Errors.fromThrowable(t).getMessage());
    }

    @Override
    public synchronized void onCompleted() {
      lost(requests, "the server ended the heartbeat stream");
    }
  }

  private void openHeartbeat(long intervalMs) {
    String id = sessionId;
    Heartbeat observer = new Heartbeat();
    synchronized (observer) {
      StreamObserver<HeartbeatRequest> hb = server.dirAsync.heartbeat(observer);
      observer.requests = hb;
      heartbeat = hb;
      beatNow =
          () -> {
            try {
              var request =
                  HeartbeatRequest.newBuilder().setSessionId(id).setState(Conversions.state(state.get())).build();
              synchronized (hb) {
                if (!transport.isClosing() && heartbeat == hb) {
                  hb.onNext(request);
                }
              }
            } catch (RuntimeException e) { // keep beating: one failed send must not end the schedule
              LOG.log(Level.FINE, "heartbeat to " + server.endpoint + " not sent", e);
            }
          };
      try {
        beat = transport.scheduler().scheduleAtFixedRate(beatNow, 0, intervalMs, TimeUnit.MILLISECONDS);
      } catch (RejectedExecutionException e) {
        // closing
      }
    }
  }

  /** The heartbeat stream {@code hb} ended: the session is gone; register again. */
  private void lost(StreamObserver<HeartbeatRequest> hb, String reason) {
    synchronized (this) {
      if (transport.isClosing() || hb == null || heartbeat != hb) {
        return;
      }
      heartbeat = null;
      beatNow = null;
    }
    ScheduledFuture<?> b = beat;
    if (b != null) {
      b.cancel(false);
    }
    LOG.warning(
        "session with " + server.endpoint + " lost (" + reason + "): its locks and tasks are released; registering again");
    transport.schedule(this::reregister, backoff.nextMillis());
  }

  private void reregister() {
    if (transport.isClosing()) {
      return;
    }
    server.channel.resetConnectBackoff();
    try {
      RegisterResponse resp = register();
      LOG.info("registered again with " + server.endpoint + " (session " + sessionId + ")");
      openHeartbeat(interval(resp));
    } catch (CastError e) {
      LOG.info("registering with " + server.endpoint + " failed (" + e.getMessage() + "); retrying");
      transport.schedule(this::reregister, backoff.nextMillis());
    }
  }

  /**
   * Report the state at once rather than at the next scheduled beat (a third of the
   * lease, seconds by default), so tools see RUNNING or STOPPING when it happens.
   */
  void report() {
    Runnable b = beatNow;
    if (b == null) {
      return;
    }
    try {
      transport.scheduler().execute(b);
    } catch (RejectedExecutionException e) {
      // closing
    }
  }

  /** How long one AwaitRun call waits before it is made again (a stop request is seen within it). */
  static final Duration AWAIT_RUN_POLL = Duration.ofSeconds(1);

  /**
   * Long-poll {@code Directory.AwaitRun} on {@code directory} until the start barrier is
   * released (true), or until {@code stopping} says the component was asked to stop or the
   * transport closes (false). DEADLINE_EXCEEDED: asked again; UNAVAILABLE: asked again after a
   * backoff (a server `cast run` restarted has no barrier and answers at once); any other
   * error is thrown: the start fails as a failing hook does.
   */
  static boolean awaitRun(GrpcTransport transport, GrpcServer directory, Transport.StopWait stopping) {
    Backoff backoff = new Backoff();
    AwaitRunRequest req = AwaitRunRequest.getDefaultInstance();
    try {
      while (!transport.isClosing() && !stopping.waitForStop(Duration.ZERO)) {
        try {
          transport.call(directory, directory.dir, AWAIT_RUN_POLL, s -> s.awaitRun(req));
          return true;
        } catch (CastError e) {
          if (e.code().equals("DEADLINE_EXCEEDED")) {
            continue; // still held
          }
          if (!e.code().equals("UNAVAILABLE")) {
            throw e;
          }
          LOG.fine("the directory at " + directory.endpoint + " is away (" + e.getMessage() + "); asking again");
        }
        if (stopping.waitForStop(Duration.ofMillis(backoff.nextMillis()))) {
          return false;
        }
      }
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
    }
    return false;
  }

  /** End the session: the server releases its locks and tasks. */
  void close() {
    ScheduledFuture<?> b = beat;
    if (b != null) {
      b.cancel(false);
    }
    StreamObserver<HeartbeatRequest> hb = heartbeat;
    if (hb != null) {
      synchronized (hb) {
        try {
          hb.onCompleted();
        } catch (RuntimeException e) {
          LOG.fine("heartbeat stream already closed: " + e.getMessage());
        }
      }
    }
  }

  /** This machine's name, as {@code cast components} shows it. */
  static String hostName() {
    try {
      return InetAddress.getLocalHost().getHostName();
    } catch (Exception e) {
      String name = ManagementFactory.getRuntimeMXBean().getName();
      int at = name.indexOf('@');
      return at < 0 ? "" : name.substring(at + 1);
    }
  }

  /**
   * Refuse to act as someone else: InvalidArgumentError naming both sides when the
   * component id that {@code idSource} gives, or the SA that {@code saSource} gives
   * (null or empty: not given), differs from what the server verified from the token.
   * {@code advice} says what to do about it.
   */
  static void requireVerified(
      Identity verified, String id, String idSource, String sa, String saSource, String advice) {
    String verifiedAs =
        "the server verified the token as component '"
            + verified.componentId()
            + "' of subarchitecture '"
            + verified.subarchitecture()
            + "'";
    if (id != null && !id.isEmpty() && !id.equals(verified.componentId())) {
      throw new InvalidArgumentError(idSource + " is '" + id + "' but " + verifiedAs + ": " + advice);
    }
    if (sa != null && !sa.isEmpty() && !sa.equals(verified.subarchitecture())) {
      throw new InvalidArgumentError(saSource + " is '" + sa + "' but " + verifiedAs + ": " + advice);
    }
  }
}
