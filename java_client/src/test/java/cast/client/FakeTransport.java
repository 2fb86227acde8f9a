package cast.client;

import com.google.protobuf.Any;
import com.google.protobuf.ByteString;
import com.google.protobuf.DescriptorProtos.FileDescriptorSet;
import java.time.Duration;
import java.time.Instant;
import java.util.ArrayList;
import java.util.HashMap;
import java.util.LinkedHashMap;
import java.util.List;
import java.util.Map;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.ConcurrentHashMap;
import java.util.concurrent.CopyOnWriteArrayList;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.ExecutorService;
import java.util.concurrent.Executors;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicInteger;
import java.util.function.BiConsumer;
import java.util.function.Consumer;
import java.util.function.Supplier;

/**
 * An in-memory {@link Transport} for unit tests of the component API: a component
 * talks to it as it talks to {@link GrpcTransport}; a test looks at what it was asked
 * and makes it answer (task decisions, a watch that ends). Components whose fakes
 * share one {@link Memory} see each other's writes, locks and events. The memory has
 * just the rules the component's side needs (versions, a lock another holds, events
 * for the matching watches, every decision adopts but "reject-me"); the real rules are
 * the server's, tested against a real server in tests/interop. Events and decisions
 * arrive on a thread of each fake's own, as a stream's reader delivers them.
 */
final class FakeTransport implements Transport {
  /** What the fakes sharing it hold, as a server would: entries, revisions, locks, what was asked. */
  static final class Memory {
    final List<String> sas;
    final Map<String, StoredEntry> entries = new HashMap<>(); // "sa/id"; guarded by this
    final Map<String, Long> revisions = new HashMap<>(); // guarded by this
    final Map<String, String> lockHolders = new ConcurrentHashMap<>(); // "sa/id" -> component id
    final List<String> calls = new CopyOnWriteArrayList<>(); // "Method sa/id ..." of every call
    final List<FileDescriptorSet> schemaRequests = new CopyOnWriteArrayList<>();
    final List<String> schemaSas = new CopyOnWriteArrayList<>(); // the SA of each schema request
    final List<FakeTransport> transports = new CopyOnWriteArrayList<>();
    final AtomicInteger tasks = new AtomicInteger();

    /** A memory holding the working memories of {@code sas}. */
    Memory(String... sas) {
      this.sas = List.of(sas);
    }
  }

  /** One watch as the component created it. */
  record Created(int watchId, List<ChangeFilter> filters, Delivery delivery) {}

  final Memory memory;
  final Identity identity; // whom "the server" says the token was issued to
  final List<String> sessions = new CopyOnWriteArrayList<>(); // "language kind" of each startSession
  final List<ComponentState> reported = new CopyOnWriteArrayList<>(); // the state at each stateChanged
  final List<Created> creates = new CopyOnWriteArrayList<>();
  final List<Integer> cancels = new CopyOnWriteArrayList<>();
  final List<List<Write>> batches = new CopyOnWriteArrayList<>();
  final Map<Integer, List<ChangeFilter>> watches = new ConcurrentHashMap<>();
  volatile Supplier<ComponentState> state;
  volatile boolean closed;
  // The start barrier: released (as a server not started by `cast run`) until a test holds it.
  private volatile CountDownLatch barrier = new CountDownLatch(0);
  final List<ComponentState> awaits = new CopyOnWriteArrayList<>(); // the state at each awaitRun
  final CountDownLatch awaiting = new CountDownLatch(1); // counted down when awaitRun is first called
  private volatile CastError barrierError; // what awaitRun throws, as a server refusing AwaitRun
  private volatile EventSink sink;
  private volatile BiConsumer<CastError, Integer> onError;
  private volatile Consumer<Task> decisions;
  // The "stream reader": events and decisions reach the component in order, on another thread.
  private final ExecutorService reader = Executors.newSingleThreadExecutor(r -> {
    Thread t = new Thread(r, "fake-transport-reader");
    t.setDaemon(true);
    return t;
  });

  FakeTransport(Memory memory, Identity identity) {
    this.memory = memory;
    this.identity = identity;
    memory.transports.add(this);
  }

  /** {@code component} bound to a fake of {@code memory} for {@code id} in {@code sa}. */
  static <C extends Component> C connect(C component, Memory memory, String id, String sa) {
    component.bind(new FakeTransport(memory, new Identity(id, sa, false)), who -> {});
    return component;
  }

  /** The fake a component is bound to. */
  static FakeTransport of(Component component) {
    return (FakeTransport) component.transport();
  }

  private static String key(String sa, String id) {
    return sa + "/" + id;
  }

  // ---------------------------------------------------------------- session

  @Override
  public Identity startSession(String language, String kind, Supplier<ComponentState> state) {
    sessions.add(language + " " + kind);
    this.state = state;
    return identity;
  }

  @Override
  public void stateChanged() {
    reported.add(state.get());
  }

  /** Hold the start barrier: awaitRun waits until {@link #releaseBarrier} (or a stop request). */
  FakeTransport holdBarrier() {
    barrier = new CountDownLatch(1);
    return this;
  }

  /** Make awaitRun fail with {@code error} (an error other than DEADLINE_EXCEEDED or UNAVAILABLE). */
  void failBarrier(CastError error) {
    barrierError = error;
  }

  /** Release the start barrier: every awaitRun returns true, now and from now on. */
  void releaseBarrier() {
    barrier.countDown();
  }

  @Override
  public boolean awaitRun(StopWait stopping) {
    awaits.add(state.get());
    awaiting.countDown();
    if (barrierError != null) {
      throw barrierError;
    }
    try {
      while (!stopping.waitForStop(Duration.ZERO)) {
        if (barrier.await(10, TimeUnit.MILLISECONDS)) {
          return true;
        }
      }
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
    }
    return false;
  }

  @Override
  public List<String> subarchitectures() {
    return memory.sas;
  }

  // ----------------------------------------------------------------- writes

  /** In private memory, as with no shared memory; its writes send its bytes (Transport's defaults). */
  @Override
  public Loan loan(String sa, String typeUrl, ByteString header, int size) {
    memory.calls.add("Loan " + sa + " " + size);
    return new Loan(sa, typeUrl, LoanMemory.of(null, header, size));
  }

  @Override
  public WriteResult add(String sa, String id, Any value) {
    memory.calls.add("Add " + key(sa, id));
    synchronized (memory) {
      if (memory.entries.containsKey(key(sa, id))) {
        throw new AlreadyExistsError("entry '" + id + "' already exists");
      }
      return write(Operation.ADD, sa, id, value, 0);
    }
  }

  @Override
  public WriteResult overwrite(String sa, String id, Any value, Long expectedVersion) {
    memory.calls.add("Overwrite " + key(sa, id));
    synchronized (memory) {
      StoredEntry old = existing(sa, id, expectedVersion);
      String holder = memory.lockHolders.get(key(sa, id));
      if (holder != null && !holder.equals(identity.componentId())) {
        throw new LockedError("locked by " + holder);
      }
      return write(Operation.OVERWRITE, sa, id, value, old.version() + 1);
    }
  }

  /** The write applied at once; its result or refusal on a completed future, as the stream's reply. */
  private static CompletableFuture<WriteResult> completed(Supplier<WriteResult> write) {
    try {
      return CompletableFuture.completedFuture(write.get());
    } catch (CastError e) {
      return CompletableFuture.failedFuture(e);
    }
  }

  @Override
  public CompletableFuture<WriteResult> addAsync(String sa, String id, Any value) {
    return completed(() -> add(sa, id, value));
  }

  @Override
  public CompletableFuture<WriteResult> overwriteAsync(String sa, String id, Any value, Long expectedVersion) {
    return completed(() -> overwrite(sa, id, value, expectedVersion));
  }

  @Override
  public WriteResult delete(String sa, String id, Long expectedVersion) {
    memory.calls.add("Delete " + key(sa, id));
    synchronized (memory) {
      StoredEntry old = existing(sa, id, expectedVersion);
      return write(Operation.DELETE, sa, id, null, old.version());
    }
  }

  private StoredEntry existing(String sa, String id, Long expectedVersion) {
    StoredEntry old = memory.entries.get(key(sa, id));
    if (old == null) {
      throw new NotFoundError("no entry '" + id + "'");
    }
    if (expectedVersion != null && expectedVersion != old.version()) {
      throw new ConsistencyError("version " + old.version() + ", not " + expectedVersion);
    }
    return old;
  }

  /** Apply one write (under the memory's lock) and send its event to every matching watch. */
  private WriteResult write(Operation op, String sa, String id, Any value, long version) {
    long revision = memory.revisions.merge(sa, 1L, Long::sum);
    WorkingMemoryAddress address = new WorkingMemoryAddress(id, sa);
    StoredEntry entry;
    if (op == Operation.DELETE) {
      entry = memory.entries.remove(key(sa, id));
    } else {
      entry = new StoredEntry(
          address, Types.typeOf(value), value.getValue(), version, identity.componentId(), revision,
          Instant.ofEpochSecond(1_700_000_000L));
      memory.entries.put(key(sa, id), entry);
    }
    for (FakeTransport t : memory.transports) {
      t.publish(new Change(revision, op, address, entry.type(), version, identity.componentId(),
          identity.subarchitecture(), entry.modified(), entry, List.of()));
    }
    return new WriteResult(revision, version);
  }

  /** Deliver {@code change} tagged with this fake's matching watches (the entry only when one asked). */
  private void publish(Change change) {
    List<Integer> ids = new ArrayList<>();
    boolean withEntry = false;
    for (var w : new LinkedHashMap<>(watches).entrySet()) {
      for (ChangeFilter f : w.getValue()) {
        if (matches(f, change)) {
          if (!ids.contains(w.getKey())) {
            ids.add(w.getKey());
          }
          withEntry |= f.includeEntry();
        }
      }
    }
    if (ids.isEmpty() || closed) {
      return;
    }
    Change tagged = new Change(change.revision(), change.operation(), change.address(), change.type(),
        change.version(), change.sourceComponent(), change.sourceSubarchitecture(), change.time(),
        withEntry ? change.entry() : null, List.copyOf(ids));
    reader.execute(() -> sink.event(tagged));
  }

  static boolean matches(ChangeFilter f, Change c) {
    return (f.operations().isEmpty() || f.operations().contains(c.operation()))
        && (f.type().isEmpty() || f.type().equals(c.type()))
        && (f.id().isEmpty() || f.id().equals(c.address().id()))
        && (f.subarchitecture().isEmpty() || f.subarchitecture().equals(c.address().subarchitecture()))
        && (f.sourceComponent().isEmpty() || f.sourceComponent().equals(c.sourceComponent()));
  }

  @Override
  public List<WriteResult> batch(String sa, List<Write> writes) {
    batches.add(writes);
    List<WriteResult> out = new ArrayList<>();
    for (Write w : writes) {
      out.add(switch (w.operation()) {
        case ADD -> add(sa, w.id(), w.value());
        case OVERWRITE -> overwrite(sa, w.id(), w.value(), w.expectedVersion());
        case DELETE -> delete(sa, w.id(), w.expectedVersion());
      });
    }
    return out;
  }

  @Override
  public void registerSchemas(FileDescriptorSet files, String sa) {
    memory.schemaRequests.add(files);
    memory.schemaSas.add(sa);
  }

  // ------------------------------------------------------------------ reads

  @Override
  public StoredEntry get(String sa, String id) {
    memory.calls.add("Get " + key(sa, id));
    synchronized (memory) {
      StoredEntry e = memory.entries.get(key(sa, id));
      if (e == null) {
        throw new NotFoundError("no entry '" + id + "'");
      }
      return e;
    }
  }

  @Override
  public List<StoredEntry> getByType(String sa, String type, int limit) {
    memory.calls.add("GetByType " + sa + "/" + type);
    List<StoredEntry> found = new ArrayList<>();
    synchronized (memory) {
      for (StoredEntry e : memory.entries.values()) {
        if (e.type().equals(type) && e.address().subarchitecture().equals(sa)) {
          found.add(e);
        }
      }
    }
    found.sort((a, b) -> Long.compare(b.revision(), a.revision()));
    return limit > 0 && found.size() > limit ? found.subList(0, limit) : found;
  }

  @Override
  public boolean exists(String sa, String id) {
    memory.calls.add("Exists " + key(sa, id));
    synchronized (memory) {
      return memory.entries.containsKey(key(sa, id));
    }
  }

  // ------------------------------------------------------------------ locks

  @Override
  public int lock(String sa, String id, LockMode mode, Duration timeout, boolean noWait) {
    memory.calls.add("Lock " + key(sa, id) + " " + mode + (noWait ? " nowait" : ""));
    String me = identity.componentId();
    String holder = memory.lockHolders.putIfAbsent(key(sa, id), me);
    if (holder == null || holder.equals(me)) {
      return 1;
    }
    if (noWait) {
      throw new LockedError("locked by " + holder);
    }
    // The fake never hands a held lock over: a blocking lock runs into its deadline.
    try {
      Thread.sleep(timeout == null ? Long.MAX_VALUE : timeout.toMillis());
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
    }
    throw new DeadlineExceededError("lock of " + key(sa, id) + " not granted within " + timeout);
  }

  @Override
  public int unlock(String sa, String id) {
    memory.calls.add("Unlock " + key(sa, id));
    if (!memory.lockHolders.remove(key(sa, id), identity.componentId())) {
      throw new LockedError("not locked by " + identity.componentId());
    }
    return 0;
  }

  // --------------------------------------------------------------- watching

  /** The sink the component set (its dispatcher's). */
  EventSink sink() {
    return sink;
  }

  @Override
  public void setEventSink(EventSink sink, BiConsumer<CastError, Integer> onError) {
    this.sink = sink;
    this.onError = onError;
  }

  @Override
  public Map<String, Long> watch(
      int watchId, List<ChangeFilter> filters, Map<String, Long> startRevisions, Delivery delivery) {
    creates.add(new Created(watchId, List.copyOf(filters), delivery));
    watches.put(watchId, List.copyOf(filters));
    Map<String, Long> now = new HashMap<>();
    synchronized (memory) {
      for (String sa : memory.sas) {
        now.put(sa, memory.revisions.getOrDefault(sa, 0L));
      }
    }
    return now;
  }

  @Override
  public void cancelWatch(int watchId) {
    cancels.add(watchId);
    watches.remove(watchId);
  }

  /** The watch {@code watchId} ends with {@code error} (-1: every watch, as a stream that ended for good). */
  void failWatch(int watchId, CastError error) {
    if (watchId < 0) {
      watches.clear();
    } else {
      watches.remove(watchId);
    }
    reader.execute(() -> onError.accept(error, watchId));
  }

  // ------------------------------------------------------------------ tasks

  @Override
  public Task propose(String name, Any data, int priority) {
    String taskId = "t" + memory.tasks.incrementAndGet();
    String sa = identity.subarchitecture();
    String me = identity.componentId();
    Task waiting = new Task(taskId, name, sa, me, priority, TaskState.WAITING, "", data);
    // Decided at once: "reject-me" tests the other hook.
    TaskState decision = name.equals("reject-me") ? TaskState.REJECTED : TaskState.ADOPTED;
    Task decided = new Task(taskId, name, sa, me, priority, decision, "", data);
    Consumer<Task> d = decisions;
    if (d != null) {
      reader.execute(() -> d.accept(decided));
    }
    return waiting;
  }

  @Override
  public void retract(String taskId) {
    memory.calls.add("Retract " + taskId);
  }

  @Override
  public void complete(String taskId, TaskOutcome outcome, String reason) {
    memory.calls.add("Complete " + taskId + " " + outcome + " " + reason);
  }

  @Override
  public void openDecisions(Consumer<Task> sink) {
    decisions = sink;
  }

  // --------------------------------------------------------------- outcomes

  /** What the component reported, in order, as "name value". */
  final List<String> reports = new CopyOnWriteArrayList<>();
  /** What report throws, as a server refusing it (null: accepted). */
  volatile CastError reportError;

  @Override
  public void report(String name, double value) {
    if (reportError != null) {
      throw reportError;
    }
    reports.add(name + " " + value);
  }

  @Override
  public void close() {
    closed = true;
    memory.transports.remove(this);
    reader.shutdown();
  }
}
