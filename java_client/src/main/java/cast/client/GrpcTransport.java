package cast.client;

import cast.v1.AddRequest;
import cast.v1.BatchRequest;
import cast.v1.ChangeEvent;
import cast.v1.CompleteRequest;
import cast.v1.DeleteRequest;
import cast.v1.DescribeSystemRequest;
import cast.v1.DecisionsRequest;
import cast.v1.DirectoryGrpc;
import cast.v1.EntryAddress;
import cast.v1.ExistsRequest;
import cast.v1.GetByTypeRequest;
import cast.v1.GetRequest;
import cast.v1.HeartbeatRequest;
import cast.v1.HeartbeatResponse;
import cast.v1.LockRequest;
import cast.v1.OverwriteRequest;
import cast.v1.ProposeRequest;
import cast.v1.RegisterRequest;
import cast.v1.RegisterResponse;
import cast.v1.RegisterSchemasRequest;
import cast.v1.RetractRequest;
import cast.v1.SubarchitectureInfo;
import cast.v1.SystemDescription;
import cast.v1.TaskManagerGrpc;
import cast.v1.UnlockRequest;
import cast.v1.WatchCancel;
import cast.v1.WatchCreate;
import cast.v1.WatchRequest;
import cast.v1.WatchResponse;
import cast.v1.WorkingMemoryGrpc;
import cast.v1.WriteResponse;
import com.google.protobuf.Any;
import com.google.protobuf.DescriptorProtos.FileDescriptorSet;
import io.grpc.CallOptions;
import io.grpc.Channel;
import io.grpc.ClientCall;
import io.grpc.ClientInterceptor;
import io.grpc.ForwardingClientCall;
import io.grpc.Grpc;
import io.grpc.ManagedChannel;
import io.grpc.ManagedChannelBuilder;
import io.grpc.Metadata;
import io.grpc.MethodDescriptor;
import io.grpc.Status;
import io.grpc.StatusRuntimeException;
import io.grpc.stub.AbstractStub;
import io.grpc.stub.ClientCallStreamObserver;
import io.grpc.stub.ClientResponseObserver;
import io.grpc.stub.StreamObserver;
import java.lang.management.ManagementFactory;
import java.net.InetAddress;
import java.time.Duration;
import java.util.ArrayList;
import java.util.HashMap;
import java.util.LinkedHashMap;
import java.util.List;
import java.util.Map;
import java.util.Set;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.ConcurrentHashMap;
import java.util.concurrent.ExecutionException;
import java.util.concurrent.Executors;
import java.util.concurrent.ScheduledExecutorService;
import java.util.concurrent.ScheduledThreadPoolExecutor;
import java.util.concurrent.ScheduledFuture;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.TimeoutException;
import java.util.concurrent.atomic.AtomicBoolean;
import java.util.concurrent.atomic.AtomicInteger;
import java.util.function.BiConsumer;
import java.util.function.Consumer;
import java.util.function.Function;
import java.util.function.Supplier;
import java.util.logging.Level;
import java.util.logging.Logger;

/**
 * A component's connection to a CAST system through its directory endpoint,
 * following docs/client-protocol.md call by call: routing by SA from
 * DescribeSystem, one Watch stream per server, a session (Register + Heartbeat
 * stream) per server, the Decisions stream of the own SA's task manager.
 *
 * <p>When a server goes away the component object stays and this class
 * reconnects (docs/client-protocol.md, "Reconnection"): unary calls fail at once
 * with UnavailableError; Watch streams are opened again with backoff and every
 * watch resumes from the revision after the last one it got (no gap, no
 * duplicate), guarded by the server's history id; sessions are registered again
 * (locks and tasks do not survive); the Decisions stream is opened again.
 */
final class GrpcTransport implements AutoCloseable {
  private static final Logger LOG = Logger.getLogger("cast.client");
  static final int MAX_MESSAGE_BYTES = 64 * 1024 * 1024;
  static final Duration DEFAULT_CALL_TIMEOUT = Duration.ofSeconds(30);
  private static final Metadata.Key<String> AUTHORIZATION =
      Metadata.Key.of("authorization", Metadata.ASCII_STRING_MARSHALLER);
  /** Stream errors after which the stream is opened again; any other ends it for good. */
  static final Set<Status.Code> TRANSIENT =
      Set.of(
          Status.Code.UNAVAILABLE,
          Status.Code.UNKNOWN,
          Status.Code.INTERNAL,
          Status.Code.CANCELLED,
          Status.Code.DEADLINE_EXCEEDED,
          Status.Code.UNAUTHENTICATED);

  /** Opens a channel to an endpoint (tests use in-process channels). */
  interface ChannelFactory {
    ManagedChannel open(String endpoint);
  }

  /** Receives change events, in the order each server sent them. */
  interface EventSink {
    void event(ChangeEvent event);
  }

  static ManagedChannel plaintextChannel(String endpoint) {
    return channel(endpoint, null);
  }

  /** A channel to {@code endpoint}, with TLS when {@code tls} is set (never falling back to plaintext). */
  static ManagedChannel channel(String endpoint, ClientTls tls) {
    ManagedChannelBuilder<?> b;
    if (tls == null) {
      b = ManagedChannelBuilder.forTarget(endpoint).usePlaintext();
    } else {
      b = Grpc.newChannelBuilder(endpoint, tls.credentials());
      if (!tls.serverName().isEmpty()) {
        b.overrideAuthority(tls.serverName());
      }
    }
    return b.maxInboundMessageSize(MAX_MESSAGE_BYTES)
        // Notice a dead server (and let it notice us) on an idle connection;
        // the server permits pings every 5 s without data.
        .keepAliveTime(10, TimeUnit.SECONDS)
        .keepAliveTimeout(5, TimeUnit.SECONDS)
        .keepAliveWithoutCalls(true)
        .build();
  }

  /** One server endpoint: its channel, stubs and per-server streams. */
  final class Server {
    final String endpoint;
    final ManagedChannel channel;
    final WorkingMemoryGrpc.WorkingMemoryBlockingStub wm;
    final WorkingMemoryGrpc.WorkingMemoryStub wmAsync;
    final TaskManagerGrpc.TaskManagerBlockingStub tm;
    final TaskManagerGrpc.TaskManagerStub tmAsync;
    final DirectoryGrpc.DirectoryBlockingStub dir;
    final DirectoryGrpc.DirectoryStub dirAsync;
    WatchStream watchStream; // guarded by GrpcTransport.this.lock
    volatile String sessionId = "";
    volatile StreamObserver<HeartbeatRequest> heartbeat; // sends guarded by the observer itself
    volatile ScheduledFuture<?> beat;
    volatile Runnable beatNow;
    final Backoff sessionBackoff = new Backoff();

    Server(String endpoint) {
      this.endpoint = endpoint;
      this.channel = channels.open(endpoint);
      ClientInterceptor auth = tokenInterceptor();
      this.wm = WorkingMemoryGrpc.newBlockingStub(channel).withInterceptors(auth);
      this.wmAsync = WorkingMemoryGrpc.newStub(channel).withInterceptors(auth);
      this.tm = TaskManagerGrpc.newBlockingStub(channel).withInterceptors(auth);
      this.tmAsync = TaskManagerGrpc.newStub(channel).withInterceptors(auth);
      this.dir = DirectoryGrpc.newBlockingStub(channel).withInterceptors(auth);
      this.dirAsync = DirectoryGrpc.newStub(channel).withInterceptors(auth);
    }
  }

  /** What the client keeps of one watch so that it can be created again after a reconnect. */
  static final class Watch {
    final int watchId;
    final List<cast.v1.ChangeFilter> filters;
    final Map<String, Long> firstStarts;
    List<String> sas = List.of(); // the SAs of this server the watch covers (known once created)
    Map<String, Long> base; // per SA, the revision the watch has seen up to (null until created)

    Watch(int watchId, List<cast.v1.ChangeFilter> filters, Map<String, Long> firstStarts) {
      this.watchId = watchId;
      this.filters = List.copyOf(filters);
      this.firstStarts = Map.copyOf(firstStarts);
    }
  }

  /**
   * The Watch stream to one server, shared by every watch of the component on that
   * server. When the connection breaks it is opened again with backoff and every
   * watch is created again from the revision after the last one it got, per SA,
   * with the server's history id: a server that lost that history refuses the
   * resume, and the component is told to resynchronise (HistoryExpiredError).
   */
  final class WatchStream {
    private final Server server;
    private final Object mutex = new Object();
    private final Map<Integer, Watch> watches = new LinkedHashMap<>(); // guarded by mutex
    private final Map<Integer, CompletableFuture<Map<String, Long>>> pending = new ConcurrentHashMap<>();
    // The newest revision per SA received on this stream: the server moves every watch of an SA
    // on one stream past the events it sends, so each watch has seen at least this far.
    private final Map<String, Long> seen = new ConcurrentHashMap<>();
    private final Backoff backoff = new Backoff();
    private ClientCallStreamObserver<WatchRequest> requests; // the current call; guarded by mutex
    private int generation; // numbers the calls; guarded by mutex
    private volatile String historyId = "";
    private volatile boolean connected;
    private volatile boolean dead; // ended for good: a new watch needs a new stream
    private volatile boolean closed;
    final AtomicInteger reconnects = new AtomicInteger();

    WatchStream(Server server) {
      this.server = server;
      open();
    }

    boolean isEnded() {
      return dead;
    }

    private WatchRequest createRequest(Watch w) {
      Map<String, Long> starts;
      String history;
      if (w.base == null) {
        starts = w.firstStarts;
        history = "";
      } else {
        starts = new HashMap<>();
        Map<String, Long> base = new HashMap<>();
        for (String sa : w.sas) {
          long upTo = Math.max(w.base.getOrDefault(sa, 0L), seen.getOrDefault(sa, 0L));
          starts.put(sa, upTo + 1);
          base.put(sa, upTo); // where the watch now is: a later resume never goes back before it
        }
        w.base = base;
        history = historyId;
      }
      return WatchRequest.newBuilder()
          .setCreate(
              WatchCreate.newBuilder()
                  .setWatchId(w.watchId)
                  .addAllFilters(w.filters)
                  .putAllStartRevisions(starts)
                  .setHistoryId(history))
          .build();
    }

    /** Send on the current call (under mutex); a call that just ended drops it, the reopen resends. */
    private void send(WatchRequest req) {
      if (requests == null) {
        return;
      }
      try {
        requests.onNext(req);
      } catch (IllegalStateException e) {
        LOG.fine("watch request not sent, the call ended: " + e.getMessage());
      }
    }

    private void open() {
      synchronized (mutex) {
        if (closed || closing.get()) {
          return;
        }
        int gen = ++generation;
        requests = null;
        server.wmAsync.watch(new Call(gen)); // beforeStart sets `requests`
        for (Watch w : watches.values()) {
          send(createRequest(w));
        }
      }
    }

    /** The observer of one Watch call. */
    private final class Call implements ClientResponseObserver<WatchRequest, WatchResponse> {
      private final int gen;

      Call(int gen) {
        this.gen = gen;
      }

      @Override
      public void beforeStart(ClientCallStreamObserver<WatchRequest> requestStream) {
        synchronized (mutex) {
          if (gen == generation) {
            requests = requestStream;
          }
        }
      }

      @Override
      public void onNext(WatchResponse resp) {
        // grpc-java calls this serially per call, so events keep the server's order.
        if (!connected) {
          connected = true;
          backoff.reset();
        }
        handle(resp);
      }

      @Override
      public void onError(Throwable t) {
        ended(gen, Status.fromThrowable(t));
      }

      @Override
      public void onCompleted() {
        ended(gen, Status.UNAVAILABLE.withDescription("the server at " + server.endpoint + " ended the watch stream"));
      }
    }

    private void handle(WatchResponse resp) {
      EventSink s = sink;
      for (ChangeEvent e : resp.getEventsList()) {
        if (s != null) {
          s.event(e);
        }
        seen.merge(e.getAddress().getSubarchitecture(), e.getRevision(), Math::max);
      }
      if (resp.hasCreated()) {
        var created = resp.getCreated();
        if (!created.getHistoryId().isEmpty()) {
          historyId = created.getHistoryId();
        }
        synchronized (mutex) {
          Watch w = watches.get(created.getWatchId());
          if (w != null && w.base == null) {
            Map<String, Long> revisions = created.getRevisionsMap();
            boolean coversAll = w.filters.stream().anyMatch(f -> f.getSubarchitecture().isEmpty());
            List<String> sas = new ArrayList<>();
            Map<String, Long> base = new HashMap<>();
            for (var r : revisions.entrySet()) {
              String sa = r.getKey();
              if (coversAll || w.filters.stream().anyMatch(f -> f.getSubarchitecture().equals(sa))) {
                sas.add(sa);
                base.put(sa, w.firstStarts.getOrDefault(sa, r.getValue() + 1) - 1);
              }
            }
            w.sas = sas;
            w.base = base;
          }
        }
        var f = pending.remove(created.getWatchId());
        if (f != null) {
          f.complete(created.getRevisionsMap());
        }
      }
      if (resp.hasFailed()) {
        var failed = resp.getFailed();
        CastError error = Errors.forCode(failed.getCode(), failed.getMessage());
        var f = pending.remove(failed.getWatchId());
        Watch dropped;
        synchronized (mutex) {
          dropped = watches.remove(failed.getWatchId());
        }
        if (f != null) {
          f.completeExceptionally(error);
        } else if (dropped != null) {
          // A resume refused after a reconnect: the history no longer covers it (or the server
          // lost it): the component must resynchronise.
          if (!(error instanceof HistoryExpiredError)) {
            error = new HistoryExpiredError("watch " + failed.getWatchId() + " could not resume: " + failed.getMessage());
          }
          onWatchError.accept(error, failed.getWatchId());
        }
      }
    }

    private void ended(int gen, Status status) {
      synchronized (mutex) {
        if (gen != generation) {
          return; // an older call
        }
        requests = null;
      }
      connected = false;
      if (closed || closing.get()) {
        return;
      }
      CastError error = Errors.fromStatus(status);
      if (!TRANSIENT.contains(status.getCode())) {
        fail(error);
        return;
      }
      reconnects.incrementAndGet();
      long delay = backoff.nextMillis();
      LOG.warning(
          "watch stream to " + server.endpoint + " broke (" + status.getCode() + ": " + status.getDescription()
              + "); reconnecting in " + delay + " ms");
      schedule(
          () -> {
            server.channel.resetConnectBackoff(); // try the server now, not after gRPC's own (long) backoff
            open();
          },
          delay);
    }

    /** End the stream for good (fell behind the history, ...): every watch on it fails. */
    private void fail(CastError error) {
      dead = true;
      synchronized (mutex) {
        watches.clear();
      }
      for (Integer id : new ArrayList<>(pending.keySet())) {
        var f = pending.remove(id);
        if (f != null) {
          f.completeExceptionally(error);
        }
      }
      onWatchError.accept(error, -1);
    }

    Map<String, Long> create(int watchId, List<cast.v1.ChangeFilter> filters, Map<String, Long> starts) {
      var done = new CompletableFuture<Map<String, Long>>();
      Watch w = new Watch(watchId, filters, starts);
      synchronized (mutex) {
        if (dead) {
          throw new UnavailableError("the watch stream to " + server.endpoint + " has ended");
        }
        pending.put(watchId, done);
        watches.put(watchId, w);
        send(createRequest(w)); // while disconnected, the reopen sends it
      }
      try {
        return done.get(callTimeout.toMillis(), TimeUnit.MILLISECONDS);
      } catch (TimeoutException e) {
        forget(watchId);
        if (!connected) {
          throw new UnavailableError(
              "server " + server.endpoint + " unreachable: the watch was not created within " + callTimeout);
        }
        throw new DeadlineExceededError(
            "the server at " + server.endpoint + " did not confirm watch " + watchId + " within " + callTimeout);
      } catch (ExecutionException e) {
        forget(watchId);
        throw Errors.fromThrowable(e.getCause());
      } catch (InterruptedException e) {
        Thread.currentThread().interrupt();
        forget(watchId);
        throw new CastError("CANCELLED", "interrupted while waiting for the server to confirm watch " + watchId);
      }
    }

    private void forget(int watchId) {
      pending.remove(watchId);
      synchronized (mutex) {
        watches.remove(watchId);
      }
    }

    void cancel(int watchId) {
      synchronized (mutex) {
        watches.remove(watchId);
        send(WatchRequest.newBuilder().setCancel(WatchCancel.newBuilder().setWatchId(watchId)).build());
      }
    }

    void close() {
      closed = true;
      synchronized (mutex) {
        if (requests != null) {
          try {
            requests.cancel("component closing", null);
          } catch (RuntimeException e) {
            LOG.fine("watch call already ended: " + e);
          }
          requests = null;
        }
      }
    }
  }

  private final String componentId;
  private final String subarchitecture;
  private final boolean privileged;
  private final TokenSource tokens;
  private final Duration callTimeout;
  private final ChannelFactory channels;
  private final Object lock = new Object();
  private final Server directory;
  private final Map<String, Server> servers = new LinkedHashMap<>(); // by endpoint; guarded by lock
  private volatile Map<String, Server> routes = Map.of();
  private volatile SystemDescription system;
  private final Map<Integer, List<Server>> watchServers = new ConcurrentHashMap<>();
  private volatile EventSink sink;
  private volatile BiConsumer<CastError, Integer> onWatchError =
      (err, watchId) -> LOG.severe("change delivery stopped: " + err.getMessage());
  private final AtomicBoolean closing = new AtomicBoolean();
  // Heartbeats, reconnects and re-registrations (two threads: a re-registration may wait on a call).
  private final ScheduledExecutorService heartbeats;
  private volatile ClientCallStreamObserver<DecisionsRequest> decisions;
  private final AtomicInteger sessions = new AtomicInteger();
  private volatile String sessionLanguage = "java";
  private volatile String sessionKind = "unmanaged";
  private volatile Supplier<cast.v1.ComponentState> sessionState =
      () -> cast.v1.ComponentState.COMPONENT_STATE_STARTING;

  GrpcTransport(LaunchContract contract) {
    this(contract, endpoint -> channel(endpoint, contract.tls()), DEFAULT_CALL_TIMEOUT);
  }

  GrpcTransport(LaunchContract contract, ChannelFactory channels, Duration callTimeout) {
    this.componentId = contract.componentId();
    this.subarchitecture = contract.subarchitecture();
    this.privileged = contract.privileged();
    this.callTimeout = callTimeout;
    this.channels = channels;
    this.tokens =
        new TokenSource(
            contract.token(), contract.tokenFile() == null ? null : java.nio.file.Path.of(contract.tokenFile()));
    ScheduledThreadPoolExecutor scheduler =
        new ScheduledThreadPoolExecutor(
            2,
            r -> {
              Thread t = new Thread(r, "cast-heartbeat-" + contract.componentId());
              t.setDaemon(true);
              return t;
            });
    scheduler.setRemoveOnCancelPolicy(true);
    this.heartbeats = scheduler;
    this.directory = new Server(contract.endpoint());
    servers.put(contract.endpoint(), directory);
    try {
      describe();
    } catch (RuntimeException e) {
      close();
      throw e;
    }
  }

  String componentId() {
    return componentId;
  }

  String subarchitecture() {
    return subarchitecture;
  }

  boolean privileged() {
    return privileged;
  }

  // ------------------------------------------------------------------ calls

  /** Adds the current token to every call (re-read from CAST_TOKEN_FILE when it changes). */
  private ClientInterceptor tokenInterceptor() {
    return new ClientInterceptor() {
      @Override
      public <Q, R> ClientCall<Q, R> interceptCall(MethodDescriptor<Q, R> method, CallOptions options, Channel next) {
        return new ForwardingClientCall.SimpleForwardingClientCall<Q, R>(next.newCall(method, options)) {
          @Override
          public void start(Listener<R> listener, Metadata headers) {
            headers.put(AUTHORIZATION, "Bearer " + tokens.token());
            super.start(listener, headers);
          }
        };
      }
    };
  }

  private <S extends AbstractStub<S>, R> R attempt(S stub, Duration timeout, Function<S, R> fn) {
    // A deadline per attempt: every call has one (30 s by default), so nothing hangs forever.
    S s = timeout == null ? stub : stub.withDeadlineAfter(timeout.toNanos(), TimeUnit.NANOSECONDS);
    return fn.apply(s);
  }

  private <S extends AbstractStub<S>, R> R call(Server server, S stub, Duration timeout, Function<S, R> fn) {
    Status status;
    try {
      return attempt(stub, timeout, fn);
    } catch (StatusRuntimeException e) {
      status = e.getStatus();
    }
    // A refused token may just have been renewed in its file: read it and try once more
    // (nothing was applied: the token is checked first).
    if (status.getCode() == Status.Code.UNAUTHENTICATED && tokens.refresh()) {
      try {
        return attempt(stub, timeout, fn);
      } catch (StatusRuntimeException e) {
        status = e.getStatus();
      }
    }
    if (status.getCode() == Status.Code.UNAVAILABLE) {
      server.channel.resetConnectBackoff(); // the next call tries the server at once
    }
    throw Errors.fromStatus(status);
  }

  private <S extends AbstractStub<S>, R> R call(Server server, S stub, Function<S, R> fn) {
    return call(server, stub, callTimeout, fn);
  }

  /** Run {@code task} on the scheduler after {@code delayMillis}, unless closing. */
  void schedule(Runnable task, long delayMillis) {
    if (closing.get()) {
      return;
    }
    try {
      heartbeats.schedule(
          () -> {
            try {
              task.run();
            } catch (RuntimeException e) { // a failed reconnect step is logged; the next one is scheduled by its owner
              LOG.log(Level.WARNING, "reconnect step failed", e);
            }
          },
          delayMillis,
          TimeUnit.MILLISECONDS);
    } catch (java.util.concurrent.RejectedExecutionException e) {
      // closing
    }
  }

  /** How many sessions this transport registered (more than one per server after reconnects). */
  int sessions() {
    return sessions.get();
  }

  // ---------------------------------------------------------------- routing

  /** Ask the directory for the system and route each SA to its server. */
  SystemDescription describe() {
    SystemDescription desc =
        call(directory, directory.dir, s -> s.describeSystem(DescribeSystemRequest.getDefaultInstance()));
    synchronized (lock) {
      Map<String, Server> r = new HashMap<>();
      for (SubarchitectureInfo sa : desc.getSubarchitecturesList()) {
        // An SA served by the answering server itself reuses the directory's channel.
        if (sa.getEndpoint().isEmpty() || sa.getEndpoint().equals(desc.getEndpoint())) {
          r.put(sa.getName(), directory);
        } else {
          r.put(sa.getName(), servers.computeIfAbsent(sa.getEndpoint(), Server::new));
        }
      }
      routes = r;
      system = desc;
    }
    return desc;
  }

  /** The system as last described by the directory. */
  SystemDescription system() {
    return system;
  }

  /** The server of an SA; an unknown SA goes to the directory's server, which answers NOT_FOUND naming the known SAs. */
  Server server(String sa) {
    return routes.getOrDefault(sa, directory);
  }

  private List<Server> allServers() {
    synchronized (lock) {
      return new ArrayList<>(servers.values());
    }
  }

  private static EntryAddress addr(String sa, String id) {
    return EntryAddress.newBuilder().setId(id).setSubarchitecture(sa).build();
  }

  private static WriteResult result(WriteResponse r) {
    return new WriteResult(r.getRevision(), r.getVersion());
  }

  // ----------------------------------------------------------------- writes

  WriteResult add(String sa, String id, Any value) {
    var req = AddRequest.newBuilder().setAddress(addr(sa, id)).setValue(value).build();
    return result(call(server(sa), server(sa).wm, s -> s.add(req)));
  }

  WriteResult overwrite(String sa, String id, Any value, Long expectedVersion) {
    var b = OverwriteRequest.newBuilder().setAddress(addr(sa, id)).setValue(value);
    if (expectedVersion != null) {
      b.setExpectedVersion(expectedVersion);
    }
    var req = b.build();
    return result(call(server(sa), server(sa).wm, s -> s.overwrite(req)));
  }

  WriteResult delete(String sa, String id, Long expectedVersion) {
    var b = DeleteRequest.newBuilder().setAddress(addr(sa, id));
    if (expectedVersion != null) {
      b.setExpectedVersion(expectedVersion);
    }
    var req = b.build();
    return result(call(server(sa), server(sa).wm, s -> s.delete(req)));
  }

  /** Apply writes in order, all or nothing, on the server of {@code sa}. */
  List<WriteResult> batch(String sa, BatchRequest req) {
    var resp = call(server(sa), server(sa).wm, s -> s.batch(req));
    List<WriteResult> out = new ArrayList<>();
    for (WriteResponse r : resp.getResultsList()) {
      out.add(result(r));
    }
    return out;
  }

  // ------------------------------------------------------------------ reads

  cast.v1.Entry get(String sa, String id) {
    var req = GetRequest.newBuilder().setAddress(addr(sa, id)).build();
    return call(server(sa), server(sa).wm, s -> s.get(req)).getEntry();
  }

  List<cast.v1.Entry> getByType(String sa, String type, int limit) {
    var req = GetByTypeRequest.newBuilder().setSubarchitecture(sa).setType(type).setLimit(limit).build();
    return call(server(sa), server(sa).wm, s -> s.getByType(req)).getEntriesList();
  }

  boolean exists(String sa, String id) {
    var req = ExistsRequest.newBuilder().setAddress(addr(sa, id)).build();
    return call(server(sa), server(sa).wm, s -> s.exists(req)).getExists();
  }

  // ------------------------------------------------------------------ locks

  /** Take a lock; a blocking lock waits up to {@code timeout} (null: forever). */
  int lock(String sa, String id, LockMode mode, Duration timeout, boolean noWait) {
    var req = LockRequest.newBuilder().setAddress(addr(sa, id)).setMode(mode.toProto()).setNoWait(noWait).build();
    return call(server(sa), server(sa).wm, noWait ? callTimeout : timeout, s -> s.lock(req)).getDepth();
  }

  int unlock(String sa, String id) {
    var req = UnlockRequest.newBuilder().setAddress(addr(sa, id)).build();
    return call(server(sa), server(sa).wm, s -> s.unlock(req)).getDepth();
  }

  // ---------------------------------------------------------------- schemas

  /** Register entry types with every server of the system. */
  void registerSchemas(FileDescriptorSet files) {
    var req = RegisterSchemasRequest.newBuilder().setFiles(files).build();
    for (Server server : allServers()) {
      call(server, server.dir, s -> s.registerSchemas(req));
    }
  }

  // --------------------------------------------------------------- watching

  void setEventSink(EventSink sink, BiConsumer<CastError, Integer> onError) {
    this.sink = sink;
    this.onWatchError = onError;
  }

  /** Create a watch on every server whose SAs its filters can match; returns the revisions at creation. */
  Map<String, Long> watch(int watchId, List<cast.v1.ChangeFilter> filters, Map<String, Long> startRevisions) {
    if (sink == null) {
      throw new IllegalStateException("setEventSink must be called before watch");
    }
    List<Server> targets = new ArrayList<>();
    for (cast.v1.ChangeFilter f : filters) {
      List<Server> candidates =
          f.getSubarchitecture().isEmpty() ? allServers() : List.of(server(f.getSubarchitecture()));
      for (Server s : candidates) {
        if (!targets.contains(s)) {
          targets.add(s);
        }
      }
    }
    Map<String, Long> revisions = new HashMap<>();
    List<Server> created = new ArrayList<>();
    try {
      for (Server server : targets) {
        WatchStream stream;
        synchronized (lock) {
          if (closing.get()) {
            throw new UnavailableError("the component's connection is closed");
          }
          // A stream that ended (server restart, history expired) is replaced, so a
          // component can register its callbacks again from watchFailed.
          if (server.watchStream == null || server.watchStream.isEnded()) {
            server.watchStream = new WatchStream(server);
          }
          stream = server.watchStream;
        }
        Map<String, Long> mine = new HashMap<>();
        startRevisions.forEach((sa, rev) -> {
          if (server(sa) == server) {
            mine.put(sa, rev);
          }
        });
        revisions.putAll(stream.create(watchId, filters, mine));
        created.add(server);
      }
    } catch (RuntimeException e) {
      // All or nothing: do not leave half a watch behind on the servers that accepted it.
      for (Server s : created) {
        s.watchStream.cancel(watchId);
      }
      throw e;
    }
    watchServers.put(watchId, targets);
    return revisions;
  }

  void cancelWatch(int watchId) {
    List<Server> targets = watchServers.remove(watchId);
    if (targets == null) {
      return;
    }
    for (Server server : targets) {
      WatchStream stream;
      synchronized (lock) {
        stream = server.watchStream;
      }
      if (stream != null) {
        stream.cancel(watchId);
      }
    }
  }

  // ------------------------------------------------------------------ tasks

  cast.v1.Task propose(String name, Any data, int priority) {
    var b = ProposeRequest.newBuilder().setName(name).setPriority(priority);
    if (data != null) {
      b.setData(data);
    }
    var req = b.build();
    return call(server(subarchitecture), server(subarchitecture).tm, s -> s.propose(req)).getTask();
  }

  void retract(String taskId) {
    var req = RetractRequest.newBuilder().setTaskId(taskId).build();
    call(server(subarchitecture), server(subarchitecture).tm, s -> s.retract(req));
  }

  void complete(String taskId, TaskOutcome outcome, String reason) {
    var req =
        CompleteRequest.newBuilder()
            .setTaskId(taskId)
            .setOutcome(outcome.toProto())
            .setReason(reason == null ? "" : reason)
            .build();
    call(server(subarchitecture), server(subarchitecture).tm, s -> s.complete(req));
  }

  /**
   * Open the decision stream of the own SA's task manager; decisions go to {@code sink}.
   * The stream is opened again (with backoff) after it broke.
   */
  void openDecisions(Consumer<cast.v1.Task> sink) {
    openDecisionStream(sink, new Backoff());
  }

  private void openDecisionStream(Consumer<cast.v1.Task> sink, Backoff backoff) {
    if (closing.get()) {
      return;
    }
    Server server = server(subarchitecture);
    server.tmAsync.decisions(
        DecisionsRequest.getDefaultInstance(),
        new ClientResponseObserver<DecisionsRequest, cast.v1.Task>() {
          @Override
          public void beforeStart(ClientCallStreamObserver<DecisionsRequest> call) {
            decisions = call;
          }

          @Override
          public void onNext(cast.v1.Task task) {
            backoff.reset();
            sink.accept(task);
          }

          @Override
          public void onError(Throwable t) {
            ended(Status.fromThrowable(t));
          }

          @Override
          public void onCompleted() {
            ended(Status.UNAVAILABLE.withDescription("the task manager ended the decision stream"));
          }

          private void ended(Status status) {
            if (closing.get()) {
              return;
            }
            if (!TRANSIENT.contains(status.getCode())) {
              onWatchError.accept(Errors.fromStatus(status), -1);
              return;
            }
            long delay = backoff.nextMillis();
            LOG.warning("decision stream broke (" + status.getCode() + "); opening it again in " + delay + " ms");
            schedule(
                () -> {
                  server.channel.resetConnectBackoff();
                  openDecisionStream(sink, backoff);
                },
                delay);
          }
        });
  }

  // --------------------------------------------------------------- sessions

  /**
   * Register with every server and keep the sessions alive with heartbeat streams.
   * A broken session is registered again with backoff: a new session, since the
   * server released the locks and tasks of the old one when it ended.
   */
  void startSession(String language, String kind, Supplier<cast.v1.ComponentState> state) {
    this.sessionLanguage = language;
    this.sessionKind = kind;
    this.sessionState = state;
    for (Server server : allServers()) {
      openHeartbeat(server, register(server));
    }
  }

  /** Register a session on {@code server}; returns the heartbeat interval in milliseconds. */
  private long register(Server server) {
    var req =
        RegisterRequest.newBuilder()
            .setLanguage(sessionLanguage)
            .setKind(sessionKind)
            .setPid(ProcessHandle.current().pid())
            .setHost(hostName())
            .build();
    RegisterResponse resp = call(server, server.dir, s -> s.register(req));
    server.sessionId = resp.getSessionId();
    sessions.incrementAndGet();
    return Math.max(50, resp.getLeaseMs() / 3);
  }

  /** One heartbeat stream of one session; sends are serialised on the object itself. */
  private final class Heartbeat implements StreamObserver<HeartbeatResponse> {
    private final Server server;
    StreamObserver<HeartbeatRequest> requests;

    Heartbeat(Server server) {
      this.server = server;
    }

    @Override
    public void onNext(HeartbeatResponse value) {
      server.sessionBackoff.reset();
    }

    // synchronized: waits until openHeartbeat has recorded the stream (a call may fail at once).
    @Override
    public synchronized void onError(Throwable t) {
      lost(server, requests, Errors.fromThrowable(t).getMessage());
    }

    @Override
    public synchronized void onCompleted() {
      lost(server, requests, "the server ended the heartbeat stream");
    }
  }

  private void openHeartbeat(Server server, long intervalMs) {
    String sessionId = server.sessionId;
    Heartbeat observer = new Heartbeat(server);
    synchronized (observer) {
      StreamObserver<HeartbeatRequest> hb = server.dirAsync.heartbeat(observer);
      observer.requests = hb;
      server.heartbeat = hb;
      server.beatNow =
          () -> {
            try {
              var beat = HeartbeatRequest.newBuilder().setSessionId(sessionId).setState(sessionState.get()).build();
              synchronized (hb) {
                if (!closing.get() && server.heartbeat == hb) {
                  hb.onNext(beat);
                }
              }
            } catch (RuntimeException e) { // keep beating: one failed send must not end the schedule
              LOG.log(Level.FINE, "heartbeat to " + server.endpoint + " not sent", e);
            }
          };
      try {
        server.beat = heartbeats.scheduleAtFixedRate(server.beatNow, 0, intervalMs, TimeUnit.MILLISECONDS);
      } catch (java.util.concurrent.RejectedExecutionException e) {
        // closing
      }
    }
  }

  /** The heartbeat stream {@code hb} of {@code server} ended: the session is gone; register again. */
  private void lost(Server server, StreamObserver<HeartbeatRequest> hb, String reason) {
    synchronized (this) {
      if (closing.get() || hb == null || server.heartbeat != hb) {
        return;
      }
      server.heartbeat = null;
      server.beatNow = null;
    }
    ScheduledFuture<?> beat = server.beat;
    if (beat != null) {
      beat.cancel(false);
    }
    LOG.warning(
        "session with "
            + server.endpoint
            + " lost ("
            + reason
            + "): its locks and tasks are released; registering again");
    schedule(() -> reregister(server), server.sessionBackoff.nextMillis());
  }

  private void reregister(Server server) {
    if (closing.get()) {
      return;
    }
    server.channel.resetConnectBackoff();
    try {
      long interval = register(server);
      LOG.info("registered again with " + server.endpoint + " (session " + server.sessionId + ")");
      openHeartbeat(server, interval);
    } catch (CastError e) {
      LOG.info("registering with " + server.endpoint + " failed (" + e.getMessage() + "); retrying");
      schedule(() -> reregister(server), server.sessionBackoff.nextMillis());
    }
  }

  /**
   * Report a new component state at once rather than at the next scheduled beat
   * (a third of the lease, seconds by default), so tools see RUNNING or STOPPING
   * when it happens.
   */
  void stateChanged() {
    if (closing.get()) {
      return;
    }
    for (Server server : allServers()) {
      Runnable beat = server.beatNow;
      if (beat != null) {
        try {
          heartbeats.execute(beat);
        } catch (java.util.concurrent.RejectedExecutionException e) {
          return; // closing
        }
      }
    }
  }

  static String hostName() {
    try {
      return InetAddress.getLocalHost().getHostName();
    } catch (Exception e) {
      String name = ManagementFactory.getRuntimeMXBean().getName();
      int at = name.indexOf('@');
      return at < 0 ? "" : name.substring(at + 1);
    }
  }

  /** End the sessions and streams, close the channels (idempotent). */
  @Override
  public void close() {
    if (!closing.compareAndSet(false, true)) {
      return;
    }
    List<Server> all = allServers();
    for (Server server : all) {
      WatchStream stream;
      synchronized (lock) {
        stream = server.watchStream;
      }
      if (stream != null) {
        stream.close();
      }
      if (server.beat != null) {
        server.beat.cancel(false);
      }
      StreamObserver<HeartbeatRequest> hb = server.heartbeat;
      if (hb != null) {
        synchronized (hb) {
          try {
            hb.onCompleted(); // the server ends the session: locks and tasks are released
          } catch (RuntimeException e) {
            LOG.fine("heartbeat stream already closed: " + e);
          }
        }
      }
    }
    var d = decisions;
    if (d != null) {
      d.cancel("component closing", null);
    }
    heartbeats.shutdownNow();
    for (Server server : all) {
      server.channel.shutdown();
    }
    for (Server server : all) {
      try {
        if (!server.channel.awaitTermination(2, TimeUnit.SECONDS)) {
          server.channel.shutdownNow();
        }
      } catch (InterruptedException e) {
        server.channel.shutdownNow();
        Thread.currentThread().interrupt();
      }
    }
  }
}
