package cast.client;

import cast.v1.DescribeSystemRequest;
import cast.v1.ExistsRequest;
import cast.v1.GetByTypeRequest;
import cast.v1.GetRequest;
import cast.v1.RegisterSchemasRequest;
import cast.v1.ReportRequest;
import cast.v1.RetractRequest;
import cast.v1.SubarchitectureInfo;
import cast.v1.SystemDescription;
import cast.v1.WriteReply;
import cast.v1.WriteRequest;
import cast.v1.WriteResponse;
import com.google.protobuf.Any;
import com.google.protobuf.ByteString;
import com.google.protobuf.DescriptorProtos.FileDescriptorSet;
import io.grpc.Status;
import io.grpc.StatusRuntimeException;
import io.grpc.stub.AbstractStub;
import java.nio.file.Path;
import java.time.Duration;
import java.util.ArrayList;
import java.util.HashMap;
import java.util.LinkedHashMap;
import java.util.List;
import java.util.Map;
import java.util.Set;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.RejectedExecutionException;
import java.util.concurrent.ScheduledExecutorService;
import java.util.concurrent.ScheduledThreadPoolExecutor;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicBoolean;
import java.util.concurrent.atomic.AtomicInteger;
import java.util.function.BiConsumer;
import java.util.function.Consumer;
import java.util.function.Function;
import java.util.function.Supplier;
import java.util.logging.Level;
import java.util.logging.Logger;

/**
 * The {@link Transport} of a component that reaches a CAST system through its
 * directory endpoint, following docs/client-protocol.md call by call: routing by
 * SA from DescribeSystem and the unary calls, with a deadline each. Each server
 * ({@link GrpcServer}: its channel and stubs) has one {@link WriteStream} (every write
 * and lock), one {@link WatchStream} and one {@link Session}; a managed component's
 * decisions come on a {@link DecisionStream};
 * {@link Credentials} puts the token on every call. The twin of
 * python/cast/client/grpc_transport.py and cpp_client/src/grpc_transport.cc.
 *
 * <p>When a server goes away the component object stays and the transport
 * reconnects (docs/client-protocol.md, "Reconnection"): unary calls fail at once
 * with UnavailableError; Watch streams resume, sessions are registered again, the
 * Decisions stream is opened again.
 */
final class GrpcTransport implements Transport {
  private static final Logger LOG = Logger.getLogger("cast.client");
  static final Duration DEFAULT_CALL_TIMEOUT = Duration.ofSeconds(30);
  /**
   * How much longer than a blocking lock's own timeout the client waits for the server's answer:
   * the server ends the wait itself at the timeout, the margin is the answer's way back.
   */
  static final Duration LOCK_REPLY_MARGIN = Duration.ofSeconds(1);
  /**
   * How long asking a server where its shared memory is may take: it is asked on the way of a
   * write or a read, within that call's time left too ({@link Budget}).
   */
  static final Duration DESCRIBE_TIMEOUT = Duration.ofSeconds(5);
  /** Stream errors after which the stream is opened again; any other ends it for good. */
  static final Set<Status.Code> TRANSIENT =
      Set.of(
          Status.Code.UNAVAILABLE,
          Status.Code.UNKNOWN,
          Status.Code.INTERNAL,
          Status.Code.CANCELLED,
          Status.Code.DEADLINE_EXCEEDED,
          Status.Code.UNAUTHENTICATED);

  private final Credentials credentials;
  private final Duration callTimeout;
  private final GrpcServer.ChannelFactory channels;
  private final Object lock = new Object();
  private final GrpcServer directory;
  private final Map<String, GrpcServer> servers = new LinkedHashMap<>(); // by endpoint; guarded by lock
  private volatile Map<String, GrpcServer> routes = Map.of();
  private volatile SystemDescription system;
  private volatile Identity identity; // as the server verified it, once the session started
  private final WatchStream.Streams watches = new WatchStream.Streams(this);
  private final AtomicBoolean closing = new AtomicBoolean();
  // Heartbeats, reconnects and re-registrations (two threads: a re-registration may wait on a call).
  private final ScheduledExecutorService scheduler;
  private volatile DecisionStream decisions;
  private final AtomicInteger sessions = new AtomicInteger();
  private final WriteStream.Worker results; // completes the futures of addAsync/overwriteAsync
  private final WriteStream.Worker pump; // sends what addAsync/overwriteAsync queued

  /** Connects to the directory of {@code contract} and describes the system (TLS as the contract says). */
  GrpcTransport(LaunchContract contract) {
    this(contract, endpoint -> GrpcServer.channel(endpoint, contract.tls()), DEFAULT_CALL_TIMEOUT);
  }

  GrpcTransport(LaunchContract contract, GrpcServer.ChannelFactory channels, Duration callTimeout) {
    this.callTimeout = callTimeout;
    this.channels = channels;
    this.credentials =
        new Credentials(contract.token(), contract.tokenFile() == null ? null : Path.of(contract.tokenFile()));
    String name = contract.componentId() == null ? "script" : contract.componentId();
    ScheduledThreadPoolExecutor pool =
        new ScheduledThreadPoolExecutor(
            2,
            r -> {
              Thread t = new Thread(r, "cast-heartbeat-" + name);
              t.setDaemon(true);
              return t;
            });
    pool.setRemoveOnCancelPolicy(true);
    this.scheduler = pool;
    this.results = new WriteStream.Worker("cast-write-results-" + name);
    this.pump = new WriteStream.Worker("cast-write-pump-" + name);
    this.directory = openServer(contract.endpoint());
    servers.put(contract.endpoint(), directory);
    try {
      describe();
    } catch (RuntimeException e) {
      close();
      throw e;
    }
  }

  /** A server at {@code endpoint}: a channel of this transport's and its credentials on every call. */
  private GrpcServer openServer(String endpoint) {
    GrpcServer server = new GrpcServer(endpoint, channels, credentials);
    // Shared memory with it when on its host (SharedLink.java), opened when first needed. The
    // server itself says where its shared memory is: it is asked, not the directory.
    var ask = DescribeSystemRequest.getDefaultInstance();
    server.shared =
        new SharedLink(
            endpoint,
            credentials::token,
            within -> {
              Duration bound = DESCRIBE_TIMEOUT.compareTo(callTimeout) < 0 ? DESCRIBE_TIMEOUT : callTimeout;
              if (within != null && within.compareTo(bound) < 0) {
                bound = within;
              }
              return call(server, server.dir, bound, s -> s.describeSystem(ask));
            });
    return server;
  }

  // ------------------------------------------------------------------ calls

  private <S extends AbstractStub<S>, R> R attempt(S stub, Duration timeout, Function<S, R> fn) {
    // A deadline per attempt: every call has one (30 s by default), so nothing hangs forever.
    S s = timeout == null ? stub : stub.withDeadlineAfter(timeout.toNanos(), TimeUnit.NANOSECONDS);
    return fn.apply(s);
  }

  /** A unary call to {@code server}, its failure as the named CAST error. */
  <S extends AbstractStub<S>, R> R call(GrpcServer server, S stub, Duration timeout, Function<S, R> fn) {
    StatusRuntimeException failure;
    try {
      return attempt(stub, timeout, fn);
    } catch (StatusRuntimeException e) {
      failure = e;
    }
    // A refused token may just have been renewed in its file: read it and try once more
    // (nothing was applied: the token is checked first).
    if (failure.getStatus().getCode() == Status.Code.UNAUTHENTICATED && credentials.refresh()) {
      try {
        return attempt(stub, timeout, fn);
      } catch (StatusRuntimeException e) {
        failure = e;
      }
    }
    if (failure.getStatus().getCode() == Status.Code.UNAVAILABLE) {
      server.channel.resetConnectBackoff(); // the next call tries the server at once
    }
    // The trailers name the precise error (TaskStateError, ...) where a code has several.
    throw Errors.fromStatus(failure.getStatus(), failure.getTrailers());
  }

  <S extends AbstractStub<S>, R> R call(GrpcServer server, S stub, Function<S, R> fn) {
    return call(server, stub, callTimeout, fn);
  }

  /** Run {@code task} on the scheduler after {@code delayMillis}, unless closing. */
  void schedule(Runnable task, long delayMillis) {
    if (closing.get()) {
      return;
    }
    try {
      scheduler.schedule(
          () -> {
            try {
              task.run();
            } catch (RuntimeException e) { // a failed reconnect step is logged; the next one is scheduled by its owner
              LOG.log(Level.WARNING, "reconnect step failed", e);
            }
          },
          delayMillis,
          TimeUnit.MILLISECONDS);
    } catch (RejectedExecutionException e) {
      // closing
    }
  }

  /** The thread pool of heartbeats and reconnects. */
  ScheduledExecutorService scheduler() {
    return scheduler;
  }

  boolean isClosing() {
    return closing.get();
  }

  Duration callTimeout() {
    return callTimeout;
  }

  void countSession() {
    sessions.incrementAndGet();
  }

  /** How many times its Watch streams were opened again after a break. */
  int watchReconnects() {
    return watches.reconnects();
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
      Map<String, GrpcServer> r = new HashMap<>();
      for (SubarchitectureInfo sa : desc.getSubarchitecturesList()) {
        // An SA served by the answering server itself reuses the directory's channel.
        if (sa.getEndpoint().isEmpty() || sa.getEndpoint().equals(desc.getEndpoint())) {
          r.put(sa.getName(), directory);
        } else {
          r.put(sa.getName(), servers.computeIfAbsent(sa.getEndpoint(), this::openServer));
        }
      }
      routes = r;
      system = desc;
    }
    return desc;
  }

  @Override
  public List<String> subarchitectures() {
    return system.getSubarchitecturesList().stream().map(SubarchitectureInfo::getName).toList();
  }

  /** The server of an SA; an unknown SA goes to the directory's server, which answers NOT_FOUND naming the known SAs. */
  GrpcServer server(String sa) {
    return routes.getOrDefault(sa, directory);
  }

  /** Every server of the system, the directory's first. */
  List<GrpcServer> allServers() {
    synchronized (lock) {
      return new ArrayList<>(servers.values());
    }
  }

  /** The server of the own SA's task manager. */
  private GrpcServer taskServer() {
    Identity who = identity;
    if (who == null) {
      throw new IllegalStateException("task calls need a session: startSession first");
    }
    return server(who.subarchitecture());
  }

  // ------------------------------------------------------- writes and reads

  /** The Write stream to the server of {@code sa}, opened by the first write (WriteStream.java). */
  WriteStream writes(String sa) {
    GrpcServer server = server(sa);
    WriteStream stream = server.writes;
    if (stream == null) {
      synchronized (lock) {
        if (server.writes == null) {
          server.writes = new WriteStream(server, credentials, callTimeout, pump);
        }
        stream = server.writes;
      }
    }
    return stream;
  }

  private WriteResult write(String sa, WriteRequest.Builder request) {
    return Conversions.result(writes(sa).call(request, callTimeout).getWrite());
  }

  // Values of at least the shared-memory threshold are staged on the server's host
  // (StagedWrite.java); opening the session on a write's way spends the write's time (Budget).

  @Override
  public WriteResult add(String sa, String id, Any value) {
    Budget budget = new Budget(callTimeout);
    StagedWrite staged = StagedWrite.to(server(sa), budget.left());
    var request = Conversions.writeAdd(sa, id, value, staged.stage(value));
    return Conversions.result(staged.call(writes(sa), request, budget).getWrite());
  }

  @Override
  public CompletableFuture<WriteResult> addAsync(String sa, String id, Any value) {
    Budget budget = new Budget(callTimeout);
    StagedWrite staged = StagedWrite.to(server(sa), budget.left());
    return staged.submit(writes(sa), Conversions.writeAdd(sa, id, value, staged.stage(value)), results, budget);
  }

  @Override
  public WriteResult overwrite(String sa, String id, Any value, Long expectedVersion) {
    Budget budget = new Budget(callTimeout);
    StagedWrite staged = StagedWrite.to(server(sa), budget.left());
    var request = Conversions.writeOverwrite(sa, id, value, expectedVersion, staged.stage(value));
    return Conversions.result(staged.call(writes(sa), request, budget).getWrite());
  }

  @Override
  public CompletableFuture<WriteResult> overwriteAsync(String sa, String id, Any value, Long expectedVersion) {
    Budget budget = new Budget(callTimeout);
    StagedWrite staged = StagedWrite.to(server(sa), budget.left());
    var request = Conversions.writeOverwrite(sa, id, value, expectedVersion, staged.stage(value));
    return staged.submit(writes(sa), request, results, budget);
  }

  // A loan is taken in the staging area of the session its writes would stage in; written in that
  // session, still live, it is named where it is (no copy), else its bytes go (StagedWrite.stage(Loan)).

  @Override
  public Loan loan(String sa, String typeUrl, ByteString header, int size) {
    Budget budget = new Budget(callTimeout);
    SharedLink link = server(sa).shared;
    SharedSession session = link == null ? null : link.writerSession(budget.left());
    return new Loan(sa, typeUrl, LoanMemory.of(session, header, size));
  }

  @Override
  public WriteResult add(String sa, String id, Loan loan) {
    Budget budget = new Budget(callTimeout);
    StagedWrite staged = stagingFor(sa, loan, budget);
    StagedWrite.Value value = staged.stage(loan);
    var request = Conversions.writeAdd(sa, id, value.value(), value.staged());
    return Conversions.result(staged.call(writes(sa), request, budget).getWrite());
  }

  @Override
  public CompletableFuture<WriteResult> addAsync(String sa, String id, Loan loan) {
    Budget budget = new Budget(callTimeout);
    StagedWrite staged = stagingFor(sa, loan, budget);
    StagedWrite.Value value = staged.stage(loan);
    return staged.submit(writes(sa), Conversions.writeAdd(sa, id, value.value(), value.staged()), results, budget);
  }

  @Override
  public WriteResult overwrite(String sa, String id, Loan loan, Long expectedVersion) {
    Budget budget = new Budget(callTimeout);
    StagedWrite staged = stagingFor(sa, loan, budget);
    StagedWrite.Value value = staged.stage(loan);
    var request = Conversions.writeOverwrite(sa, id, value.value(), expectedVersion, value.staged());
    return Conversions.result(staged.call(writes(sa), request, budget).getWrite());
  }

  @Override
  public CompletableFuture<WriteResult> overwriteAsync(String sa, String id, Loan loan, Long expectedVersion) {
    Budget budget = new Budget(callTimeout);
    StagedWrite staged = stagingFor(sa, loan, budget);
    StagedWrite.Value value = staged.stage(loan);
    var request = Conversions.writeOverwrite(sa, id, value.value(), expectedVersion, value.staged());
    return staged.submit(writes(sa), request, results, budget);
  }

  /**
   * Staging for the write of {@code loan} to {@code sa} ({@link StagedWrite#to}); when that fails
   * (the call's time is up before anything was sent), the loan's place goes back.
   */
  private StagedWrite stagingFor(String sa, Loan loan, Budget budget) {
    try {
      return StagedWrite.to(server(sa), budget.left());
    } catch (RuntimeException e) {
      loan.memory().giveBack();
      throw e;
    }
  }

  @Override
  public WriteResult delete(String sa, String id, Long expectedVersion) {
    return write(sa, Conversions.writeDelete(sa, id, expectedVersion));
  }

  @Override
  public List<WriteResult> batch(String sa, List<Write> writes) {
    Budget budget = new Budget(callTimeout);
    // The batch's values, in the session with its server.
    StagedWrite staged = StagedWrite.to(server(sa), budget.left());
    var reply = staged.call(writes(sa), Conversions.writeBatch(sa, writes, staged::stage), budget);
    List<WriteResult> out = new ArrayList<>();
    for (WriteResponse r : reply.getBatch().getResultsList()) {
      out.add(Conversions.result(r));
    }
    return out;
  }

  @Override
  public void registerSchemas(FileDescriptorSet files, String sa) {
    var req = RegisterSchemasRequest.newBuilder().setFiles(files).build();
    GrpcServer server = server(sa);
    call(server, server.dir, s -> s.registerSchemas(req));
  }

  /**
   * A large value is lent by shared memory when on the server's host (docs/client-protocol.md);
   * opening the session on the read's way spends the read's time ({@link Budget}). With a session
   * whose server answers gets on its socket ({@link SharedSession#reads}), the get goes there, a
   * frame each way instead of a unary call, after the component's writes ({@link #getOnSocket});
   * else, or when the session cannot take it, the unary Get.
   */
  @Override
  public StoredEntry get(String sa, String id) {
    GrpcServer server = server(sa);
    Budget budget = new Budget(callTimeout);
    // With the token of the moment: after a renewal, the new session (whose HELLO's token is the
    // identity the get is answered as) once the old one's writes were answered.
    SharedSession session = server.shared == null ? null : server.shared.writerSession(budget.left());
    if (session != null && session.reads) {
      StoredEntry entry = getOnSocket(sa, id, session, budget);
      if (entry != null) {
        return entry;
      }
    }
    var req = GetRequest.newBuilder().setAddress(Conversions.address(sa, id)).build();
    SharedSession.ReadCall read = SharedLink.newCall(server.shared, budget.left());
    boolean answered = false;
    try {
      var reply = call(server, SharedLink.lending(server.wm, read), budget.left(), s -> s.get(req));
      StoredEntry entry = Conversions.entry(reply.getEntry(), read);
      answered = true;
      return entry;
    } finally {
      if (read != null) {
        read.end(answered); // RECEIVED: what the call sent and this client did not get is taken back
      }
    }
  }

  /**
   * {@code get} of entry {@code id} as a {@code WriteRequest} on {@code session}'s socket
   * (docs/client-protocol.md, "Writes on the session's socket"), its large value lent on a read
   * call of that session, which then ends as a unary read's does; null when the session cannot
   * take it: it ended (before the get was sent, or before its reply: a read changes nothing, so
   * it is made again), or it refused its token (which expired: the unary call reads the renewed
   * one).
   */
  private StoredEntry getOnSocket(String sa, String id, SharedSession session, Budget budget) {
    SharedSession.ReadCall read = session.newCall();
    WriteRequest.Builder request = WriteRequest.newBuilder().setReadCall(read.number);
    request.getGetBuilder().setAddress(Conversions.address(sa, id));
    boolean answered = false;
    try {
      WriteReply reply;
      try {
        reply = writes(sa).read(session, request, budget.left());
      } catch (UnauthenticatedError e) {
        reply = null; // refused: nothing was lent on the call
      } catch (UnavailableError e) {
        return null; // the session ended under the get: what it lent went back with it
      }
      if (reply == null) {
        answered = true; // nothing came on the call: nothing to say of it
        return null;
      }
      StoredEntry entry = Conversions.entry(reply.getGet().getEntry(), read);
      answered = true;
      return entry;
    } finally {
      read.end(answered); // RECEIVED: what the server lent and this client did not get is taken back
    }
  }

  @Override
  public List<StoredEntry> getByType(String sa, String type, int limit) {
    var req = GetByTypeRequest.newBuilder().setSubarchitecture(sa).setType(type).setLimit(limit).build();
    GrpcServer server = server(sa);
    Budget budget = new Budget(callTimeout);
    SharedSession.ReadCall read = SharedLink.newCall(server.shared, budget.left());
    List<StoredEntry> out = new ArrayList<>();
    boolean answered = false;
    try {
      var reply = call(server, SharedLink.lending(server.wm, read), budget.left(), s -> s.getByType(req));
      for (cast.v1.Entry e : reply.getEntriesList()) {
        out.add(Conversions.entry(e, read));
      }
      answered = true;
      return out;
    } finally {
      if (!answered) {
        out.forEach(StoredEntry::release); // a value that could not be read fails the call: give back the rest
      }
      if (read != null) {
        read.end(answered);
      }
    }
  }

  @Override
  public boolean exists(String sa, String id) {
    var req = ExistsRequest.newBuilder().setAddress(Conversions.address(sa, id)).build();
    return call(server(sa), server(sa).wm, s -> s.exists(req)).getExists();
  }

  @Override
  public int lock(String sa, String id, LockMode mode, Duration timeout, boolean noWait) {
    var request = Conversions.writeLock(sa, id, mode, noWait, timeout);
    // The server ends a blocking lock's wait itself (DEADLINE_EXCEEDED after `timeout`; null: it
    // waits as long as it takes); the margin covers the round trip.
    Duration wait = noWait ? callTimeout : timeout == null ? null : timeout.plus(LOCK_REPLY_MARGIN);
    return writes(sa).call(request, wait).getLock().getDepth();
  }

  @Override
  public int unlock(String sa, String id) {
    return writes(sa).call(Conversions.writeUnlock(sa, id), callTimeout).getUnlock().getDepth();
  }

  // --------------------------------------------------------------- watching

  @Override
  public void setEventSink(EventSink sink, BiConsumer<CastError, Integer> onError) {
    watches.setSink(sink, onError);
  }

  /** Where change delivery that stopped for good is reported (as {@link #setEventSink} said). */
  BiConsumer<CastError, Integer> watchErrors() {
    return watches.errors();
  }

  @Override
  public Map<String, Long> watch(
      int watchId, List<ChangeFilter> filters, Map<String, Long> startRevisions, Delivery delivery) {
    return watches.create(watchId, filters, startRevisions, delivery);
  }

  @Override
  public void cancelWatch(int watchId) {
    watches.cancel(watchId);
  }

  // ------------------------------------------------------------------ tasks

  @Override
  public Task propose(String name, Any data, int priority) {
    var req = Conversions.propose(name, data, priority);
    GrpcServer server = taskServer();
    return Conversions.task(call(server, server.tm, s -> s.propose(req)).getTask());
  }

  @Override
  public void retract(String taskId) {
    var req = RetractRequest.newBuilder().setTaskId(taskId).build();
    GrpcServer server = taskServer();
    call(server, server.tm, s -> s.retract(req));
  }

  @Override
  public void complete(String taskId, TaskOutcome outcome, String reason) {
    var req = Conversions.complete(taskId, outcome, reason);
    GrpcServer server = taskServer();
    call(server, server.tm, s -> s.complete(req));
  }

  /** Opens the decision stream of the own SA's task manager (opened again after it broke). */
  @Override
  public void openDecisions(Consumer<Task> sink) {
    decisions = new DecisionStream(this, taskServer(), sink);
  }

  /** To the own SA's server, as task calls go; {@code cast stats} merges every server's. */
  @Override
  public void report(String name, double value) {
    var req = ReportRequest.newBuilder().setName(name).setValue(value).build();
    Identity who = identity; // null only before a session (never for a component): the directory's server
    GrpcServer server = who == null ? directory : server(who.subarchitecture());
    call(server, server.insp, s -> s.report(req));
  }

  // --------------------------------------------------------------- sessions

  /** Registers with every server (the directory's first); the identity is the directory's answer. */
  @Override
  public Identity startSession(String language, String kind, Supplier<ComponentState> state) {
    Identity verified = null;
    for (GrpcServer server : allServers()) {
      Session session = new Session(this, server, language, kind, state);
      server.session = session;
      Identity who = session.open();
      if (verified == null) {
        verified = who;
      }
    }
    if (verified.componentId().isEmpty()) {
      // A server from before RegisterResponse said who the caller is: nothing to go on.
      throw new CastError(
          "UNIMPLEMENTED",
          "the server at " + directory.endpoint + " does not say whom the token was issued to: it is older than"
              + " this client library; update the server");
    }
    identity = verified;
    return verified;
  }

  @Override
  public void stateChanged() {
    if (closing.get()) {
      return;
    }
    for (GrpcServer server : allServers()) {
      Session session = server.session;
      if (session != null) {
        session.report();
      }
    }
  }

  @Override
  public boolean awaitRun(StopWait stopping) {
    return Session.awaitRun(this, directory, stopping); // the start barrier is the directory's
  }

  /** End the sessions and streams, close the channels (idempotent). */
  @Override
  public void close() {
    if (!closing.compareAndSet(false, true)) {
      return;
    }
    List<GrpcServer> all = allServers();
    for (GrpcServer server : all) {
      WriteStream writes = server.writes;
      if (writes != null) {
        writes.close(Duration.ofSeconds(2)); // outstanding replies first: they may be async results
      }
    }
    pump.shutdown();
    results.shutdown(); // what is queued still runs
    watches.close();
    for (GrpcServer server : all) {
      SharedLink shared = server.shared;
      if (shared != null) {
        shared.close(); // the server gives back what the session holds lent
      }
    }
    for (GrpcServer server : all) {
      Session session = server.session;
      if (session != null) {
        session.close(); // the server ends the session: locks and tasks are released
      }
    }
    DecisionStream d = decisions;
    if (d != null) {
      d.close();
    }
    scheduler.shutdownNow();
    for (GrpcServer server : all) {
      server.channel.shutdown();
    }
    for (GrpcServer server : all) {
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
