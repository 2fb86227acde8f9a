package cast.client;

import com.google.protobuf.Any;
import com.google.protobuf.Descriptors.FieldDescriptor;
import com.google.protobuf.Message;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.TimeUnit;
import java.util.function.Consumer;
import java.util.logging.Logger;

/**
 * What every component can do (docs/design.md section 5); subclass
 * {@link UnmanagedComponent} or {@link ManagedComponent} and override the hooks.
 *
 * <p>Every working-memory call is addressed to the component's own
 * subarchitecture unless an SA is given. Values are protobuf messages, which are
 * immutable in Java: a write sends the value's bytes and a read parses a fresh
 * object, so a component never shares a mutable object with the working memory.
 * Every method may be called from any thread. Callbacks and hooks run on one
 * dispatcher thread per component, one at a time, in the order the changes and
 * decisions arrived (revision order per working memory). The filter helpers
 * ({@code localTypeFilter}, ...) are static methods of {@link Filters}.
 */
public abstract class Component implements AutoCloseable {
  private ComponentBinding binding; // null until connected (ComponentBinding.java)
  private final Schemas.Registered schemas = new Schemas.Registered();
  private final CountDownLatch stopping = new CountDownLatch(1);
  private volatile ComponentState state = ComponentState.STARTING;

  // ------------------------------------------------------------- lifecycle

  /** Called first, with the component's {@code args} from the configuration. */
  public void configure(Args args) throws Exception {}

  /** Called after configure, before run: register callbacks here. */
  public void start() throws Exception {}

  /** The main loop; by default waits until the component is asked to stop. */
  public void run() throws Exception {
    waitForStop();
  }

  /** Called once on shutdown (SIGINT/SIGTERM, {@link #requestStop()}, or a failure of the hooks). */
  public void stop() throws Exception {}

  /** The kind reported to the directory ("managed" or "unmanaged"). */
  abstract String kind();

  // --------------------------------------------------------------- binding

  /**
   * Attach to a system (done by the runner, not by users): start the session, learn
   * from the server who this component is, and let {@code verify} refuse that identity
   * (InvalidArgumentError when the launch environment says otherwise). On failure the
   * transport is closed and the component stays unconnected.
   */
  void bind(Transport transport, Consumer<Identity> verify) {
    if (this.binding != null) {
      throw new IllegalStateException("component " + componentId() + " is already connected");
    }
    this.binding = new ComponentBinding(this, transport, () -> state, verify);
    bindExtra(transport);
  }

  /**
   * How many callbacks may wait on the dispatcher before the component stops
   * reading its change streams (default 10,000). Past it the component lags on
   * the server instead of buffering without bound, and past the server's history
   * {@link #watchFailed} receives a HistoryExpiredError. Called once, when the
   * component connects.
   */
  protected int maxPendingCallbacks() {
    return 10_000;
  }

  /** Subclasses open their extra streams here (after the session started). */
  void bindExtra(Transport transport) {}

  /** Report a new life stage to the server at once. */
  void setState(ComponentState state) {
    this.state = state;
    if (binding != null) {
      binding.transport.stateChanged();
    }
  }

  private ComponentBinding b() {
    ComponentBinding bound = binding;
    if (bound == null) {
      throw new IllegalStateException(
          getClass().getName()
              + " is not connected: run it with `java cast.client.Runner "
              + getClass().getName()
              + "`, or connect it with Runner.connect(component, contract)");
    }
    return bound;
  }

  private Transport t() {
    return b().transport;
  }

  /** The transport, for the task calls of managed components (and tests). */
  Transport transport() {
    return t();
  }

  /** Close the connection: queued callbacks run, then the session ends (locks and tasks released). */
  @Override
  public void close() {
    if (binding != null) {
      binding.close();
    }
  }

  /** This component's id, as the server verified it from the token. */
  public String componentId() {
    return b().identity.componentId(); // an unconnected component says how to connect it
  }

  /** This component's own subarchitecture, as the server verified it from the token. */
  public String subarchitecture() {
    return b().identity.subarchitecture();
  }

  /** Whether this component may write every SA, as the server verified it from the token. */
  public boolean isPrivileged() {
    return b().identity.privileged();
  }

  /** False once the component has been asked to stop. */
  public boolean isRunning() {
    return stopping.getCount() > 0;
  }

  /** Sleep until asked to stop. */
  public void waitForStop() throws InterruptedException {
    stopping.await();
  }

  /** Sleep until asked to stop (true) or {@code timeout} passes (false); use in run() loops. */
  public boolean waitForStop(Duration timeout) throws InterruptedException {
    return stopping.await(timeout.toNanos(), TimeUnit.NANOSECONDS);
  }

  /** Ask the runner to stop this component (stop() is then called once). */
  public void requestStop() {
    stopping.countDown();
  }

  /** A logger named after the component. */
  public Logger log() {
    return Logger.getLogger("cast.component." + (binding == null ? getClass().getSimpleName() : componentId()));
  }

  /** The names of the system's SAs, as the directory described them at connection. */
  public List<String> subarchitectures() {
    return t().subarchitectures();
  }

  // ------------------------------------------------------------- WM: write

  /** A fresh entry id, unique across components and restarts. */
  public String newId() {
    return b().newId();
  }

  private String sa(String subarchitecture) {
    return subarchitecture == null || subarchitecture.isEmpty() ? subarchitecture() : subarchitecture;
  }

  /**
   * The value as a write into {@code subarchitecture} (null: the own SA) sends it, after
   * registering its type's schema with that SA's server once.
   */
  Any serialise(Message value, String subarchitecture) {
    return schemas.pack(value, sa(subarchitecture), t());
  }

  /** Create an entry in the own SA; AlreadyExistsError if the id is taken. */
  public WriteResult add(String id, Message value) {
    return add(id, value, null);
  }

  /** Create an entry in {@code subarchitecture} (privileged components only, for other SAs). */
  public WriteResult add(String id, Message value, String subarchitecture) {
    Any any = serialise(value, subarchitecture);
    return t().add(sa(subarchitecture), id, any);
  }

  /**
   * Create an entry in the own SA without waiting for the server: the future of its result,
   * completed when the reply arrives; a refusal (AlreadyExistsError, ...) arrives on it. Writes
   * are applied in call order, synchronous and asynchronous alike. See {@link
   * #overwriteAsync(String, Message, String, Long)}.
   */
  public CompletableFuture<WriteResult> addAsync(String id, Message value) {
    return addAsync(id, value, null);
  }

  /** Create an entry in {@code subarchitecture} without waiting: the future of its result. */
  public CompletableFuture<WriteResult> addAsync(String id, Message value, String subarchitecture) {
    Any any = serialise(value, subarchitecture);
    return t().addAsync(sa(subarchitecture), id, any);
  }

  /** Replace an entry's value in the own SA; NotFoundError if it does not exist. */
  public WriteResult overwrite(String id, Message value) {
    return overwrite(id, value, null, null);
  }

  /** Replace an entry's value if its version is {@code expectedVersion}, else ConsistencyError. */
  public WriteResult overwrite(String id, Message value, long expectedVersion) {
    return overwrite(id, value, null, expectedVersion);
  }

  /** Replace an entry's value in {@code subarchitecture}. */
  public WriteResult overwrite(String id, Message value, String subarchitecture) {
    return overwrite(id, value, subarchitecture, null);
  }

  /** Replace an entry's value in {@code subarchitecture}, checking its version unless it is null. */
  public WriteResult overwrite(String id, Message value, String subarchitecture, Long expectedVersion) {
    Any any = serialise(value, subarchitecture);
    return t().overwrite(sa(subarchitecture), id, any, expectedVersion);
  }

  /** Replace an entry's value in the own SA without waiting: the future of its result. */
  public CompletableFuture<WriteResult> overwriteAsync(String id, Message value) {
    return overwriteAsync(id, value, null, null);
  }

  /** Replace an entry's value if its version is {@code expectedVersion}, without waiting. */
  public CompletableFuture<WriteResult> overwriteAsync(String id, Message value, long expectedVersion) {
    return overwriteAsync(id, value, null, expectedVersion);
  }

  /** Replace an entry's value in {@code subarchitecture} without waiting. */
  public CompletableFuture<WriteResult> overwriteAsync(String id, Message value, String subarchitecture) {
    return overwriteAsync(id, value, subarchitecture, null);
  }

  /**
   * Replace an entry's value in {@code subarchitecture}, checking its version unless it is
   * null, without waiting for the server: many writes may be in flight at once. The future
   * completes when the reply arrives, on the component's write-results thread, in reply order;
   * a refusal arrives on it as the error {@link #overwrite} would throw ({@code get()} wraps it
   * in an ExecutionException, {@code join()} in a CompletionException). A continuation may make
   * any call, but should not block waiting for another write's future (compose them instead).
   */
  public CompletableFuture<WriteResult> overwriteAsync(
      String id, Message value, String subarchitecture, Long expectedVersion) {
    Any any = serialise(value, subarchitecture);
    return t().overwriteAsync(sa(subarchitecture), id, any, expectedVersion);
  }

  // ------------------------------------------------------- WM: loans

  /**
   * A loan of {@code size} bytes of {@code value}'s field {@code field}, for a write to the own SA:
   * see {@link #loan(Message, String, int, String)}.
   */
  public Loan loan(Message value, String field, int size) {
    return loan(value, field, size, null);
  }

  /**
   * A large value written in place ({@link Loan}): the place of the {@code size} bytes of {@code
   * value}'s field {@code field}, a top-level singular {@code bytes} field left empty in {@code
   * value} (every other field set), to fill through {@link Loan#buffer()} and then write with
   * {@code add}, {@code overwrite}, {@code addAsync} or {@code overwriteAsync} to {@code
   * subarchitecture} (null: the own SA). On the server's host, for a large value, the buffer is in
   * shared memory and the write copies nothing. Registers the value's type as a write of it does.
   * InvalidArgumentError, nothing reserved, when {@code field} is not such a field, already holds
   * bytes, or {@code size} is negative.
   */
  public Loan loan(Message value, String field, int size, String subarchitecture) {
    FieldDescriptor loaned = LoanHeader.field(value, field, size);
    String target = sa(subarchitecture);
    Any any = serialise(value, target);
    return t().loan(target, any.getTypeUrl(), LoanHeader.of(any.getValue(), loaned, size), size);
  }

  /**
   * {@code loan}, spent for a write to {@code sa} ({@link Loan#spendFor}): InvalidArgumentError,
   * nothing written, when it is null, was written or closed, or was taken for another SA.
   */
  private static Loan spent(Loan loan, String sa) {
    if (loan == null) {
      throw new InvalidArgumentError("a loan to write was expected, got null: take one with loan(value, field, size)");
    }
    loan.spendFor(sa);
    return loan;
  }

  /**
   * Create an entry in the own SA with a loan's value ({@link #loan}); AlreadyExistsError if the id
   * is taken. The loan is spent, whatever the outcome; its buffer must not be touched any more.
   */
  public WriteResult add(String id, Loan loan) {
    return add(id, loan, null);
  }

  /** Create an entry in {@code subarchitecture} with a loan's value (taken for that SA). */
  public WriteResult add(String id, Loan loan, String subarchitecture) {
    String target = sa(subarchitecture);
    return t().add(target, id, spent(loan, target));
  }

  /** Create an entry in the own SA with a loan's value without waiting: the future of its result. */
  public CompletableFuture<WriteResult> addAsync(String id, Loan loan) {
    return addAsync(id, loan, null);
  }

  /** Create an entry in {@code subarchitecture} with a loan's value without waiting. */
  public CompletableFuture<WriteResult> addAsync(String id, Loan loan, String subarchitecture) {
    String target = sa(subarchitecture);
    return t().addAsync(target, id, spent(loan, target));
  }

  /**
   * Replace an entry's value in the own SA with a loan's ({@link #loan}); NotFoundError if it does
   * not exist. The loan is spent, whatever the outcome; its buffer must not be touched any more.
   */
  public WriteResult overwrite(String id, Loan loan) {
    return overwrite(id, loan, null, null);
  }

  /** Replace an entry's value with a loan's if its version is {@code expectedVersion}, else ConsistencyError. */
  public WriteResult overwrite(String id, Loan loan, long expectedVersion) {
    return overwrite(id, loan, null, expectedVersion);
  }

  /** Replace an entry's value in {@code subarchitecture} with a loan's. */
  public WriteResult overwrite(String id, Loan loan, String subarchitecture) {
    return overwrite(id, loan, subarchitecture, null);
  }

  /** Replace an entry's value in {@code subarchitecture} with a loan's, checking its version unless it is null. */
  public WriteResult overwrite(String id, Loan loan, String subarchitecture, Long expectedVersion) {
    String target = sa(subarchitecture);
    return t().overwrite(target, id, spent(loan, target), expectedVersion);
  }

  /** Replace an entry's value in the own SA with a loan's without waiting: the future of its result. */
  public CompletableFuture<WriteResult> overwriteAsync(String id, Loan loan) {
    return overwriteAsync(id, loan, null, null);
  }

  /** Replace an entry's value with a loan's if its version is {@code expectedVersion}, without waiting. */
  public CompletableFuture<WriteResult> overwriteAsync(String id, Loan loan, long expectedVersion) {
    return overwriteAsync(id, loan, null, expectedVersion);
  }

  /** Replace an entry's value in {@code subarchitecture} with a loan's without waiting. */
  public CompletableFuture<WriteResult> overwriteAsync(String id, Loan loan, String subarchitecture) {
    return overwriteAsync(id, loan, subarchitecture, null);
  }

  /**
   * Replace an entry's value in {@code subarchitecture} with a loan's, checking its version unless
   * it is null, without waiting: as {@link #overwriteAsync(String, Message, String, Long)}. The
   * loan is spent when this returns, whatever the outcome; its buffer must not be touched any more.
   */
  public CompletableFuture<WriteResult> overwriteAsync(
      String id, Loan loan, String subarchitecture, Long expectedVersion) {
    String target = sa(subarchitecture);
    return t().overwriteAsync(target, id, spent(loan, target), expectedVersion);
  }

  /**
   * Delete an entry of the own SA (its locks go with it). Named {@code deleteEntry}
   * in every language, since {@code delete} is a C++ keyword.
   */
  public WriteResult deleteEntry(String id) {
    return deleteEntry(id, null, null);
  }

  /** Delete an entry if its version is {@code expectedVersion}, else ConsistencyError. */
  public WriteResult deleteEntry(String id, long expectedVersion) {
    return deleteEntry(id, null, expectedVersion);
  }

  /** Delete an entry of {@code subarchitecture}. */
  public WriteResult deleteEntry(String id, String subarchitecture) {
    return deleteEntry(id, subarchitecture, null);
  }

  /** Delete an entry of {@code subarchitecture}, checking its version unless it is null. */
  public WriteResult deleteEntry(String id, String subarchitecture, Long expectedVersion) {
    return t().delete(sa(subarchitecture), id, expectedVersion);
  }

  /**
   * A batch of writes to the own SA, applied in order, all or nothing, by {@link Batch#apply()}.
   * A batch takes messages, not loans: write a {@link Loan} with add or overwrite.
   */
  public Batch batch() {
    return new Batch(this, subarchitecture());
  }

  /** A batch of writes to {@code subarchitecture}. */
  public Batch batch(String subarchitecture) {
    return new Batch(this, sa(subarchitecture));
  }

  List<WriteResult> applyBatch(String sa, List<Transport.Write> writes) {
    return t().batch(sa, writes);
  }

  // -------------------------------------------------------------- WM: read

  /** The value of an entry of the own SA as a new {@code cls} object; NotFoundError, InvalidArgumentError. */
  public <T extends Message> T get(String id, Class<T> cls) {
    return get(id, cls, null);
  }

  /** The value of an entry of {@code subarchitecture}. */
  public <T extends Message> T get(String id, Class<T> cls, String subarchitecture) {
    Types.defaultInstance(cls); // a bad class fails before the call
    Transport.StoredEntry e = t().get(sa(subarchitecture), id);
    try {
      return Types.decodeEntry(cls, e);
    } finally {
      e.release(); // a value lent by shared memory is given back once copied into the message
    }
  }

  /**
   * The value of an entry of the own SA, serialised, as a read-only buffer that is not a copy
   * ({@link ValueView}): on the server's host a large value is the server's shared memory,
   * lent while the view is open; elsewhere the bytes received. NotFoundError if missing.
   * Close the view (try-with-resources) when done with it.
   */
  public ValueView getView(String id) {
    return getView(id, null);
  }

  /** The value of an entry of {@code subarchitecture} as a {@link ValueView}. */
  public ValueView getView(String id, String subarchitecture) {
    return new ValueView(t().get(sa(subarchitecture), id));
  }

  /** An entry of the own SA with its version and author (for versioned overwrites). */
  public <T extends Message> Entry<T> getEntry(String id, Class<T> cls) {
    return getEntry(id, cls, null);
  }

  /** An entry of {@code subarchitecture} with its metadata. */
  public <T extends Message> Entry<T> getEntry(String id, Class<T> cls, String subarchitecture) {
    Types.defaultInstance(cls);
    Transport.StoredEntry e = t().get(sa(subarchitecture), id);
    try {
      return Entry.decode(e, cls);
    } finally {
      e.release();
    }
  }

  /** Every entry of type {@code cls} in the own SA, newest first. */
  public <T extends Message> List<Entry<T>> getAll(Class<T> cls) {
    return getAll(cls, null, 0);
  }

  /** Every entry of type {@code cls} in {@code subarchitecture}, newest first. */
  public <T extends Message> List<Entry<T>> getAll(Class<T> cls, String subarchitecture) {
    return getAll(cls, subarchitecture, 0);
  }

  /** The newest {@code limit} entries of type {@code cls} (0: all) in {@code subarchitecture}. */
  public <T extends Message> List<Entry<T>> getAll(Class<T> cls, String subarchitecture, int limit) {
    if (limit < 0) {
      throw new InvalidArgumentError("limit must be 0 (no limit) or positive, got " + limit);
    }
    String type = Types.typeName(cls);
    List<Transport.StoredEntry> stored = t().getByType(sa(subarchitecture), type, limit);
    List<Entry<T>> out = new ArrayList<>();
    try {
      for (Transport.StoredEntry e : stored) {
        out.add(Entry.decode(e, cls));
      }
    } finally {
      stored.forEach(Transport.StoredEntry::release);
    }
    return out;
  }

  /** Whether an entry exists in the own SA. */
  public boolean exists(String id) {
    return exists(id, null);
  }

  /** Whether an entry exists in {@code subarchitecture}. */
  public boolean exists(String id, String subarchitecture) {
    return t().exists(sa(subarchitecture), id);
  }

  // ----------------------------------------------------------------- locks

  /** Lock an entry of the own SA in mode OD, waiting as long as another component holds it. */
  public LockGuard lock(String id) {
    return lock(id, LockMode.OD, null, null);
  }

  /** Lock an entry of the own SA, waiting as long as another component holds it. */
  public LockGuard lock(String id, LockMode mode) {
    return lock(id, mode, null, null);
  }

  /** Lock an entry of the own SA, waiting up to {@code timeout} (null: forever); DeadlineExceededError after it. */
  public LockGuard lock(String id, LockMode mode, Duration timeout) {
    return lock(id, mode, null, timeout);
  }

  /**
   * Lock an entry, waiting up to {@code timeout} (null: forever) for another
   * holder. Re-entrant. Use as {@code try (LockGuard g = lock(id, mode)) { ... }}
   * to unlock at the end.
   */
  public LockGuard lock(String id, LockMode mode, String subarchitecture, Duration timeout) {
    String target = sa(subarchitecture);
    int depth = t().lock(target, id, mode == null ? LockMode.OD : mode, timeout, false);
    return new LockGuard(this, new WorkingMemoryAddress(id, target), depth);
  }

  /** Lock an entry of the own SA in mode OD if no other component holds it; never waits. */
  public boolean tryLock(String id) {
    return tryLock(id, LockMode.OD, null);
  }

  /** Lock an entry of the own SA if no other component holds it; never waits. */
  public boolean tryLock(String id, LockMode mode) {
    return tryLock(id, mode, null);
  }

  /** Lock an entry of {@code subarchitecture} if no other component holds it; never waits. */
  public boolean tryLock(String id, LockMode mode, String subarchitecture) {
    try {
      t().lock(sa(subarchitecture), id, mode == null ? LockMode.OD : mode, null, true);
      return true;
    } catch (LockedError e) {
      return false;
    }
  }

  /** Release one level of this component's lock on an entry of the own SA; returns the remaining depth. */
  public int unlock(String id) {
    return unlock(id, null);
  }

  /** Release one level of this component's lock on an entry of {@code subarchitecture}. */
  public int unlock(String id, String subarchitecture) {
    return t().unlock(sa(subarchitecture), id);
  }

  // -------------------------------------------------------------- outcomes

  /**
   * Report a measured outcome ({@code report("answers_correct", 1)}) for experiments to
   * read: the server keeps per name the count, sum, min, max and last value this component
   * reported ({@code cast stats}, {@code cast run --summary-json}, {@code cast sweep}).
   * InvalidArgumentError for an empty name or one over 128 bytes, or a value that is not
   * finite; ResourceExhaustedError past 256 names. A refused report records nothing.
   */
  public void report(String name, double value) {
    t().report(name == null ? "" : name, value);
  }

  // -------------------------------------------------------------- watching

  /** {@code callback} for each change matching {@code filter}; see {@link #onChange(List, ChangeCallback)}. */
  public WatchHandle onChange(ChangeFilter filter, ChangeCallback callback) {
    return onChange(List.of(filter), callback, WatchOptions.defaults());
  }

  /** {@code callback} for changes matching {@code filter}, delivered as {@code options} say. */
  public WatchHandle onChange(ChangeFilter filter, ChangeCallback callback, WatchOptions options) {
    return onChange(List.of(filter), callback, options);
  }

  /**
   * Call {@code callback} on the dispatcher thread for each change matching any of
   * {@code filters}, in revision order. Returns once the servers confirmed the
   * watch, so a change made after this returns is never missed.
   */
  public WatchHandle onChange(List<ChangeFilter> filters, ChangeCallback callback) {
    return onChange(filters, callback, WatchOptions.defaults());
  }

  /**
   * As {@link #onChange(List, ChangeCallback)}, delivered as {@code options} say: {@code
   * WatchOptions.latest()} (only the newest undelivered change of each entry, {@link
   * WorkingMemoryChange#skipped()} counting the ones it replaced) and {@code
   * .priority(Priority.HIGH)} (run before the component's pending MEDIUM and LOW callbacks).
   */
  public WatchHandle onChange(List<ChangeFilter> filters, ChangeCallback callback, WatchOptions options) {
    if (options == null) {
      throw new InvalidArgumentError("onChange options must not be null: use WatchOptions.defaults()");
    }
    if (filters == null || filters.isEmpty()) {
      throw new InvalidArgumentError("onChange needs at least one filter");
    }
    if (callback == null) {
      throw new InvalidArgumentError("onChange needs a callback");
    }
    // "Local" filters mean this component's own SA, which only its binding knows.
    return b().watch(filters, callback, options);
  }

  /**
   * Called on the dispatcher when change delivery stopped, e.g. with
   * HistoryExpiredError: the component fell behind the server's history, or a
   * server restarted without the history a watch was resuming from. The default
   * logs it; override to resynchronise: read the current state, then register the
   * callbacks again. (After an ordinary disconnect the library resumes every watch
   * by itself, with no gap and no duplicate.)
   */
  public void watchFailed(CastError error) throws Exception {
    log().severe(componentId() + ": change delivery stopped: " + error.getClass().getSimpleName() + ": " + error.getMessage());
  }

  /** Run a hook on the dispatcher thread, logging its failure. */
  void submit(Dispatcher.Hook hook) {
    binding.dispatcher.submitHook(hook);
  }

  /** Wait until every callback queued so far has run (tests, orderly shutdown); false on timeout. */
  public boolean drain(Duration timeout) throws InterruptedException {
    return binding == null || binding.dispatcher.drain(timeout);
  }

  /** Callbacks and hooks queued or running on the dispatcher (for tests). */
  long pendingCallbacks() {
    return binding == null ? 0 : binding.dispatcher.pending();
  }

  /** The dispatcher running this component's callbacks, or null before it is bound (for tests). */
  Dispatcher dispatcher() {
    return binding == null ? null : binding.dispatcher;
  }

  /** Whether the calling thread is this component's dispatcher thread. */
  public boolean onDispatcherThread() {
    return binding != null && Thread.currentThread() == binding.dispatcher.thread();
  }
}
