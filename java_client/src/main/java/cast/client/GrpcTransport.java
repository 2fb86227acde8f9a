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
import io.grpc.ManagedChannel;
import io.grpc.ManagedChannelBuilder;
import io.grpc.Metadata;
import io.grpc.StatusRuntimeException;
import io.grpc.stub.AbstractStub;
import io.grpc.stub.ClientCallStreamObserver;
import io.grpc.stub.ClientResponseObserver;
import io.grpc.stub.MetadataUtils;
import io.grpc.stub.StreamObserver;
import java.lang.management.ManagementFactory;
import java.net.InetAddress;
import java.time.Duration;
import java.util.ArrayList;
import java.util.HashMap;
import java.util.LinkedHashMap;
import java.util.List;
import java.util.Map;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.ConcurrentHashMap;
import java.util.concurrent.ExecutionException;
import java.util.concurrent.Executors;
import java.util.concurrent.ScheduledExecutorService;
import java.util.concurrent.ScheduledFuture;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.TimeoutException;
import java.util.concurrent.atomic.AtomicBoolean;
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
 */
final class GrpcTransport implements AutoCloseable {
  private static final Logger LOG = Logger.getLogger("cast.client");
  static final int MAX_MESSAGE_BYTES = 64 * 1024 * 1024;
  static final Duration DEFAULT_CALL_TIMEOUT = Duration.ofSeconds(30);
  private static final Metadata.Key<String> AUTHORIZATION =
      Metadata.Key.of("authorization", Metadata.ASCII_STRING_MARSHALLER);

  /** Opens a channel to an endpoint (tests use in-process channels). */
  interface ChannelFactory {
    ManagedChannel open(String endpoint);
  }

  /** Receives change events, in the order each server sent them. */
  interface EventSink {
    void event(ChangeEvent event);
  }

  static ManagedChannel plaintextChannel(String endpoint) {
    return ManagedChannelBuilder.forTarget(endpoint)
        .usePlaintext()
        .maxInboundMessageSize(MAX_MESSAGE_BYTES)
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
    StreamObserver<HeartbeatRequest> heartbeat; // guarded by itself once set
    ScheduledFuture<?> beat;
    Runnable beatNow;

    Server(String endpoint) {
      this.endpoint = endpoint;
      this.channel = channels.open(endpoint);
      var auth = MetadataUtils.newAttachHeadersInterceptor(metadata);
      this.wm = WorkingMemoryGrpc.newBlockingStub(channel).withInterceptors(auth);
      this.wmAsync = WorkingMemoryGrpc.newStub(channel).withInterceptors(auth);
      this.tm = TaskManagerGrpc.newBlockingStub(channel).withInterceptors(auth);
      this.tmAsync = TaskManagerGrpc.newStub(channel).withInterceptors(auth);
      this.dir = DirectoryGrpc.newBlockingStub(channel).withInterceptors(auth);
      this.dirAsync = DirectoryGrpc.newStub(channel).withInterceptors(auth);
    }
  }

  /** One Watch call to one server, shared by every watch of the component on that server. */
  final class WatchStream implements ClientResponseObserver<WatchRequest, WatchResponse> {
    private final Server server;
    private final Map<Integer, CompletableFuture<Map<String, Long>>> pending = new ConcurrentHashMap<>();
    private ClientCallStreamObserver<WatchRequest> requests; // guarded by this
    private volatile boolean ended;

    WatchStream(Server server) {
      this.server = server;
      server.wmAsync.watch(this);
    }

    @Override
    public void beforeStart(ClientCallStreamObserver<WatchRequest> requestStream) {
      synchronized (this) {
        this.requests = requestStream;
      }
    }

    boolean isEnded() {
      return ended;
    }

    @Override
    public void onNext(WatchResponse resp) {
      // grpc-java calls this serially per call, so events keep the server's order.
      EventSink s = sink;
      if (s != null) {
        for (ChangeEvent e : resp.getEventsList()) {
          s.event(e);
        }
      }
      if (resp.hasCreated()) {
        var f = pending.remove(resp.getCreated().getWatchId());
        if (f != null) {
          f.complete(resp.getCreated().getRevisionsMap());
        }
      }
      if (resp.hasFailed()) {
        var f = pending.remove(resp.getFailed().getWatchId());
        if (f != null) {
          f.completeExceptionally(Errors.forCode(resp.getFailed().getCode(), resp.getFailed().getMessage()));
        }
      }
    }

    @Override
    public void onError(Throwable t) {
      end(Errors.fromThrowable(t));
    }

    @Override
    public void onCompleted() {
      end(new UnavailableError("the server at " + server.endpoint + " ended the watch stream"));
    }

    private void end(CastError err) {
      ended = true;
      for (Integer id : new ArrayList<>(pending.keySet())) {
        var f = pending.remove(id);
        if (f != null) {
          f.completeExceptionally(err);
        }
      }
      if (!closing.get()) {
        onWatchError.accept(err);
      }
    }

    private void send(WatchRequest req) {
      synchronized (this) {
        requests.onNext(req);
      }
    }

    Map<String, Long> create(int watchId, List<cast.v1.ChangeFilter> filters, Map<String, Long> starts) {
      var done = new CompletableFuture<Map<String, Long>>();
      pending.put(watchId, done);
      if (ended) {
        pending.remove(watchId);
        throw new UnavailableError("the watch stream to " + server.endpoint + " has ended");
      }
      send(
          WatchRequest.newBuilder()
              .setCreate(
                  WatchCreate.newBuilder()
                      .setWatchId(watchId)
                      .addAllFilters(filters)
                      .putAllStartRevisions(starts))
              .build());
      try {
        return done.get(callTimeout.toMillis(), TimeUnit.MILLISECONDS);
      } catch (TimeoutException e) {
        pending.remove(watchId);
        throw new DeadlineExceededError(
            "the server at " + server.endpoint + " did not confirm watch " + watchId + " within " + callTimeout);
      } catch (ExecutionException e) {
        throw Errors.fromThrowable(e.getCause());
      } catch (InterruptedException e) {
        Thread.currentThread().interrupt();
        pending.remove(watchId);
        throw new CastError("CANCELLED", "interrupted while waiting for the server to confirm watch " + watchId);
      }
    }

    void cancel(int watchId) {
      if (!ended) {
        send(WatchRequest.newBuilder().setCancel(WatchCancel.newBuilder().setWatchId(watchId)).build());
      }
    }

    void close() {
      synchronized (this) {
        if (requests != null && !ended) {
          requests.cancel("component closing", null);
        }
      }
    }
  }

  private final String componentId;
  private final String subarchitecture;
  private final boolean privileged;
  private final Metadata metadata = new Metadata();
  private final Duration callTimeout;
  private final ChannelFactory channels;
  private final Object lock = new Object();
  private final Server directory;
  private final Map<String, Server> servers = new LinkedHashMap<>(); // by endpoint; guarded by lock
  private volatile Map<String, Server> routes = Map.of();
  private volatile SystemDescription system;
  private final Map<Integer, List<Server>> watchServers = new ConcurrentHashMap<>();
  private volatile EventSink sink;
  private volatile Consumer<CastError> onWatchError =
      err -> LOG.severe("change delivery stopped: " + err.getMessage());
  private final AtomicBoolean closing = new AtomicBoolean();
  private final ScheduledExecutorService heartbeats;
  private volatile ClientCallStreamObserver<DecisionsRequest> decisions;

  GrpcTransport(LaunchContract contract) {
    this(contract, GrpcTransport::plaintextChannel, DEFAULT_CALL_TIMEOUT);
  }

  GrpcTransport(LaunchContract contract, ChannelFactory channels, Duration callTimeout) {
    this.componentId = contract.componentId();
    this.subarchitecture = contract.subarchitecture();
    this.privileged = contract.privileged();
    this.callTimeout = callTimeout;
    this.channels = channels;
    this.metadata.put(AUTHORIZATION, "Bearer " + contract.token());
    this.heartbeats =
        Executors.newSingleThreadScheduledExecutor(
            r -> {
              Thread t = new Thread(r, "cast-heartbeat-" + contract.componentId());
              t.setDaemon(true);
              return t;
            });
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

  private <S extends AbstractStub<S>, R> R call(S stub, Duration timeout, Function<S, R> fn) {
    S s = timeout == null ? stub : stub.withDeadlineAfter(timeout.toNanos(), TimeUnit.NANOSECONDS);
    try {
      return fn.apply(s);
    } catch (StatusRuntimeException e) {
      throw Errors.fromStatus(e.getStatus());
    }
  }

  private <S extends AbstractStub<S>, R> R call(S stub, Function<S, R> fn) {
    return call(stub, callTimeout, fn);
  }

  // ---------------------------------------------------------------- routing

  /** Ask the directory for the system and route each SA to its server. */
  SystemDescription describe() {
    SystemDescription desc = call(directory.dir, s -> s.describeSystem(DescribeSystemRequest.getDefaultInstance()));
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
    return result(call(server(sa).wm, s -> s.add(req)));
  }

  WriteResult overwrite(String sa, String id, Any value, Long expectedVersion) {
    var b = OverwriteRequest.newBuilder().setAddress(addr(sa, id)).setValue(value);
    if (expectedVersion != null) {
      b.setExpectedVersion(expectedVersion);
    }
    var req = b.build();
    return result(call(server(sa).wm, s -> s.overwrite(req)));
  }

  WriteResult delete(String sa, String id, Long expectedVersion) {
    var b = DeleteRequest.newBuilder().setAddress(addr(sa, id));
    if (expectedVersion != null) {
      b.setExpectedVersion(expectedVersion);
    }
    var req = b.build();
    return result(call(server(sa).wm, s -> s.delete(req)));
  }

  /** Apply writes in order, all or nothing, on the server of {@code sa}. */
  List<WriteResult> batch(String sa, BatchRequest req) {
    var resp = call(server(sa).wm, s -> s.batch(req));
    List<WriteResult> out = new ArrayList<>();
    for (WriteResponse r : resp.getResultsList()) {
      out.add(result(r));
    }
    return out;
  }

  // ------------------------------------------------------------------ reads

  cast.v1.Entry get(String sa, String id) {
    var req = GetRequest.newBuilder().setAddress(addr(sa, id)).build();
    return call(server(sa).wm, s -> s.get(req)).getEntry();
  }

  List<cast.v1.Entry> getByType(String sa, String type, int limit) {
    var req = GetByTypeRequest.newBuilder().setSubarchitecture(sa).setType(type).setLimit(limit).build();
    return call(server(sa).wm, s -> s.getByType(req)).getEntriesList();
  }

  boolean exists(String sa, String id) {
    var req = ExistsRequest.newBuilder().setAddress(addr(sa, id)).build();
    return call(server(sa).wm, s -> s.exists(req)).getExists();
  }

  // ------------------------------------------------------------------ locks

  /** Take a lock; a blocking lock waits up to {@code timeout} (null: forever). */
  int lock(String sa, String id, LockMode mode, Duration timeout, boolean noWait) {
    var req = LockRequest.newBuilder().setAddress(addr(sa, id)).setMode(mode.toProto()).setNoWait(noWait).build();
    return call(server(sa).wm, noWait ? callTimeout : timeout, s -> s.lock(req)).getDepth();
  }

  int unlock(String sa, String id) {
    var req = UnlockRequest.newBuilder().setAddress(addr(sa, id)).build();
    return call(server(sa).wm, s -> s.unlock(req)).getDepth();
  }

  // ---------------------------------------------------------------- schemas

  /** Register entry types with every server of the system. */
  void registerSchemas(FileDescriptorSet files) {
    var req = RegisterSchemasRequest.newBuilder().setFiles(files).build();
    for (Server server : allServers()) {
      call(server.dir, s -> s.registerSchemas(req));
    }
  }

  // --------------------------------------------------------------- watching

  void setEventSink(EventSink sink, Consumer<CastError> onError) {
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
    return call(server(subarchitecture).tm, s -> s.propose(req)).getTask();
  }

  void retract(String taskId) {
    var req = RetractRequest.newBuilder().setTaskId(taskId).build();
    call(server(subarchitecture).tm, s -> s.retract(req));
  }

  void complete(String taskId, TaskOutcome outcome, String reason) {
    var req =
        CompleteRequest.newBuilder()
            .setTaskId(taskId)
            .setOutcome(outcome.toProto())
            .setReason(reason == null ? "" : reason)
            .build();
    call(server(subarchitecture).tm, s -> s.complete(req));
  }

  /** Open the decision stream of the own SA's task manager; decisions go to {@code sink}. */
  void openDecisions(Consumer<cast.v1.Task> sink) {
    server(subarchitecture)
        .tmAsync
        .decisions(
            DecisionsRequest.getDefaultInstance(),
            new ClientResponseObserver<DecisionsRequest, cast.v1.Task>() {
              @Override
              public void beforeStart(ClientCallStreamObserver<DecisionsRequest> call) {
                decisions = call;
              }

              @Override
              public void onNext(cast.v1.Task task) {
                sink.accept(task);
              }

              @Override
              public void onError(Throwable t) {
                if (!closing.get()) {
                  onWatchError.accept(Errors.fromThrowable(t));
                }
              }

              @Override
              public void onCompleted() {
                if (!closing.get()) {
                  onWatchError.accept(new UnavailableError("the task manager ended the decision stream"));
                }
              }
            });
  }

  // --------------------------------------------------------------- sessions

  /** Register with every server and keep the sessions alive with heartbeat streams. */
  void startSession(String language, String kind, Supplier<cast.v1.ComponentState> state) {
    var req =
        RegisterRequest.newBuilder()
            .setLanguage(language)
            .setKind(kind)
            .setPid(ProcessHandle.current().pid())
            .setHost(hostName())
            .build();
    for (Server server : allServers()) {
      RegisterResponse resp = call(server.dir, s -> s.register(req));
      server.sessionId = resp.getSessionId();
      long intervalMs = Math.max(50, resp.getLeaseMs() / 3);
      StreamObserver<HeartbeatRequest> hb =
          server.dirAsync.heartbeat(
              new StreamObserver<HeartbeatResponse>() {
                @Override
                public void onNext(HeartbeatResponse value) {}

                @Override
                public void onError(Throwable t) {
                  if (!closing.get()) {
                    LOG.severe("heartbeat to " + server.endpoint + " failed: " + Errors.fromThrowable(t).getMessage());
                  }
                }

                @Override
                public void onCompleted() {
                  if (!closing.get()) {
                    LOG.severe("the server at " + server.endpoint + " ended the session's heartbeat stream");
                  }
                }
              });
      server.heartbeat = hb;
      server.beatNow =
          () -> {
            try {
              var beat = HeartbeatRequest.newBuilder().setSessionId(server.sessionId).setState(state.get()).build();
              synchronized (hb) {
                if (!closing.get()) {
                  hb.onNext(beat);
                }
              }
            } catch (RuntimeException e) { // keep beating: one failed send must not end the schedule
              LOG.log(Level.WARNING, "heartbeat to " + server.endpoint + " not sent", e);
            }
          };
      server.beat = heartbeats.scheduleAtFixedRate(server.beatNow, 0, intervalMs, TimeUnit.MILLISECONDS);
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

  private static String hostName() {
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
      if (server.heartbeat != null) {
        synchronized (server.heartbeat) {
          try {
            server.heartbeat.onCompleted(); // the server ends the session: locks and tasks are released
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
