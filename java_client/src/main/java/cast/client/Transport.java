package cast.client;

import com.google.protobuf.Any;
import com.google.protobuf.ByteString;
import com.google.protobuf.DescriptorProtos.FileDescriptorSet;
import java.time.Duration;
import java.time.Instant;
import java.util.List;
import java.util.Map;
import java.util.concurrent.CompletableFuture;
import java.util.function.BiConsumer;
import java.util.function.Consumer;
import java.util.function.Supplier;

/**
 * The boundary between the component API and the way it reaches the working
 * memories: everything a component does to working memories, its task manager and
 * its session, in the library's own types (no generated {@code cast.v1} message
 * crosses it). {@link GrpcTransport} speaks gRPC to the servers; the unit tests use
 * an in-memory fake. The twin of python/cast/client/transport.py and
 * cpp_client/src/transport.h.
 *
 * <p>Every call except {@link #startSession} is made after {@link #startSession}
 * returned. Calls that name an SA go to the server of that SA; task calls go to the
 * task manager of the component's own SA, as the server verified it.
 */
interface Transport extends AutoCloseable {

  /**
   * An entry as stored, its value still bytes: the transport does not know the class
   * the caller will read it as.
   *
   * @param address where the entry lives
   * @param type full protobuf name of the value's type
   * @param value the serialised value (when lent, a wrapper of the lease's bytes, not a copy)
   * @param version the entry's version
   * @param author id of the component that made the last write
   * @param revision the working memory's revision of the last write
   * @param modified server time of the last write
   * @param lease the value lent by shared memory, held once for this entry, or null when its
   *     bytes were received: whoever is handed the entry gives it back ({@link #release()}) or
   *     passes it on
   */
  record StoredEntry(
      WorkingMemoryAddress address,
      String type,
      ByteString value,
      long version,
      String author,
      long revision,
      Instant modified,
      Lease lease) {

    /** An entry whose bytes were received. */
    StoredEntry(
        WorkingMemoryAddress address, String type, ByteString value, long version, String author, long revision,
        Instant modified) {
      this(address, type, value, version, author, revision, modified, null);
    }

    /** Let go of the value if it was lent (its bytes must not be read through this entry afterwards). */
    void release() {
      if (lease != null) {
        lease.release();
      }
    }

    /**
     * One more holder of a lent value; false when it was given back already (then its bytes
     * must not be read). Always true for bytes received.
     */
    boolean retain() {
      return lease == null || lease.retain();
    }
  }

  /**
   * One change event, once, with the ids of every watch of this component it matched.
   *
   * @param revision the working memory's revision of the change
   * @param operation ADD, OVERWRITE or DELETE
   * @param address the entry changed
   * @param type full name of the entry's type
   * @param version the entry's version after the change (DELETE: the version it had)
   * @param sourceComponent id of the writer
   * @param sourceSubarchitecture SA of the writer
   * @param time server time of the change
   * @param entry the entry (after the write; DELETE: as it was), or null when no filter asked for it
   * @param watchIds the matching watches of this component
   * @param skipped how many earlier changes of the entry a LATEST watch did not receive (0: none)
   * @param firstSkippedRevision the revision of the oldest of them (0: none)
   */
  record Change(
      long revision,
      Operation operation,
      WorkingMemoryAddress address,
      String type,
      long version,
      String sourceComponent,
      String sourceSubarchitecture,
      Instant time,
      StoredEntry entry,
      List<Integer> watchIds,
      long skipped,
      long firstSkippedRevision) {

    /** A change that replaced none. */
    Change(
        long revision,
        Operation operation,
        WorkingMemoryAddress address,
        String type,
        long version,
        String sourceComponent,
        String sourceSubarchitecture,
        Instant time,
        StoredEntry entry,
        List<Integer> watchIds) {
      this(revision, operation, address, type, version, sourceComponent, sourceSubarchitecture, time, entry,
          watchIds, 0, 0);
    }

    /**
     * This change in place of {@code older}, an undelivered change of the same entry: it
     * skipped that one and what that one skipped (the oldest skipped revision is kept).
     */
    Change superseding(Change older) {
      long first = older.firstSkippedRevision != 0 ? older.firstSkippedRevision : older.revision;
      return new Change(revision, operation, address, type, version, sourceComponent, sourceSubarchitecture, time,
          entry, watchIds, skipped + older.skipped + 1, first);
    }
  }

  /**
   * One write of a batch.
   *
   * @param operation what to do
   * @param id the entry's id (in the batch's SA)
   * @param value the value to write (null for DELETE)
   * @param expectedVersion the version the entry must have, or null for any
   */
  record Write(Operation operation, String id, Any value, Long expectedVersion) {}

  /** Receives change events, in the order each server sent them (revision order per WM). */
  interface EventSink {
    /** One event; may block while the component's queue is full (the stream then waits). */
    void event(Change change);

    /**
     * One event, as {@link #event(Change)}, but queued over the component's capacity rather than
     * waiting while {@code overflow} holds (a shared-memory session's reader: SharedSession).
     */
    default void event(Change change, java.util.function.BooleanSupplier overflow) {
      event(change);
    }

    /**
     * A watch call's events come on {@code socket}, a shared-memory session's: the component's
     * dispatcher may read it itself while it has nothing to run ({@link Dispatcher#attach}); by
     * default the socket's reader thread does.
     */
    default void readBy(SessionSocket socket) {}
  }

  // ---------------------------------------------------------------- session

  /**
   * Register with every server and keep the sessions alive, reporting {@code state()};
   * returns the identity the server verified from the token (the component is that,
   * whatever its launch environment says).
   */
  Identity startSession(String language, String kind, Supplier<ComponentState> state);

  /** Report the state now rather than at the next heartbeat. */
  void stateChanged();

  /** Sleeps up to {@code timeout} or until the component is asked to stop; true if it was. */
  interface StopWait {
    boolean waitForStop(Duration timeout) throws InterruptedException;
  }

  /**
   * Wait at the start barrier (a component `cast run` launched, state STARTED): returns true
   * once every component of the system has started and run() may begin, false when
   * {@code stopping} says the component was asked to stop first (or the transport closes).
   */
  boolean awaitRun(StopWait stopping);

  /** The names of the system's SAs, as the directory described them. */
  List<String> subarchitectures();

  // ----------------------------------------------------------------- writes

  /** Create an entry; AlreadyExistsError if the id is taken. */
  WriteResult add(String sa, String id, Any value);

  /** Create an entry without waiting: the future of its result (errors arrive on it). */
  CompletableFuture<WriteResult> addAsync(String sa, String id, Any value);

  /** Replace an entry's value, checking its version unless {@code expectedVersion} is null. */
  WriteResult overwrite(String sa, String id, Any value, Long expectedVersion);

  /** Replace an entry's value without waiting: the future of its result (errors arrive on it). */
  CompletableFuture<WriteResult> overwriteAsync(String sa, String id, Any value, Long expectedVersion);

  /**
   * A loan of {@code size} bytes after {@code header} (made by {@link LoanHeader}) for a value of
   * {@code typeUrl} to be written to {@code sa}: in the staging area of that SA's server when the
   * value would go by shared memory, else private memory ({@link LoanMemory#of}).
   */
  Loan loan(String sa, String typeUrl, ByteString header, int size);

  // A loan's writes: the loan was spent for {@code sa} ({@link Loan#spendFor}), its memory is the
  // write's. A transport without shared memory sends its bytes, as these defaults do.

  /** Create an entry with a loan's value. */
  default WriteResult add(String sa, String id, Loan loan) {
    return add(sa, id, loan.value());
  }

  /** Create an entry with a loan's value without waiting. */
  default CompletableFuture<WriteResult> addAsync(String sa, String id, Loan loan) {
    return addAsync(sa, id, loan.value());
  }

  /** Replace an entry's value with a loan's, checking its version unless {@code expectedVersion} is null. */
  default WriteResult overwrite(String sa, String id, Loan loan, Long expectedVersion) {
    return overwrite(sa, id, loan.value(), expectedVersion);
  }

  /** Replace an entry's value with a loan's without waiting. */
  default CompletableFuture<WriteResult> overwriteAsync(String sa, String id, Loan loan, Long expectedVersion) {
    return overwriteAsync(sa, id, loan.value(), expectedVersion);
  }

  /** Delete an entry, checking its version unless {@code expectedVersion} is null. */
  WriteResult delete(String sa, String id, Long expectedVersion);

  /** Apply writes to one SA in order, all or nothing; one result per write. */
  List<WriteResult> batch(String sa, List<Write> writes);

  /** Register entry types (their files and every import) with the server of {@code sa}. */
  void registerSchemas(FileDescriptorSet files, String sa);

  // ------------------------------------------------------------------ reads

  /** One entry; NotFoundError if there is none. */
  StoredEntry get(String sa, String id);

  /** The newest {@code limit} entries (0: all) of a type, newest first. */
  List<StoredEntry> getByType(String sa, String type, int limit);

  /** Whether an entry exists. */
  boolean exists(String sa, String id);

  // ------------------------------------------------------------------ locks

  /** Take a lock, waiting up to {@code timeout} (null: forever) unless {@code noWait}; returns its depth. */
  int lock(String sa, String id, LockMode mode, Duration timeout, boolean noWait);

  /** Release one level of a lock; returns the remaining depth. */
  int unlock(String sa, String id);

  // --------------------------------------------------------------- watching

  /**
   * Where events go, and where a watch's end goes: {@code onError(error, watchId)} for
   * one watch that could not resume (it is dropped), {@code watchId} -1 for all of them.
   */
  void setEventSink(EventSink sink, BiConsumer<CastError, Integer> onError);

  /**
   * Create a watch (filters with their SA filled in; "" for every SA) delivered as
   * {@code delivery} says; returns once the servers confirmed it, with each SA's revision
   * when it took effect.
   */
  Map<String, Long> watch(
      int watchId, List<ChangeFilter> filters, Map<String, Long> startRevisions, Delivery delivery);

  /** Remove a watch. */
  void cancelWatch(int watchId);

  // ------------------------------------------------------------------ tasks

  /** Propose a task (data may be null) to the own SA's task manager. */
  Task propose(String name, Any data, int priority);

  /** Withdraw a task. */
  void retract(String taskId);

  /** Report an adopted task's outcome. */
  void complete(String taskId, TaskOutcome outcome, String reason);

  /** Deliver every decision about this component's tasks to {@code sink}, from now on. */
  void openDecisions(Consumer<Task> sink);

  // --------------------------------------------------------------- outcomes

  /** Record an outcome the component measured with its own SA's server (Inspection.Report). */
  void report(String name, double value);

  /** End the sessions (locks and tasks released) and every stream (idempotent). */
  @Override
  void close();
}
