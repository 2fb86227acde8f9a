package cast.client;

import cast.v1.AddRequest;
import cast.v1.BatchOperation;
import cast.v1.BatchRequest;
import cast.v1.CompleteRequest;
import cast.v1.DeleteRequest;
import cast.v1.EntryAddress;
import cast.v1.LockRequest;
import cast.v1.OverwriteRequest;
import cast.v1.ProposeRequest;
import cast.v1.RegisterResponse;
import cast.v1.StagedValue;
import cast.v1.UnlockRequest;
import cast.v1.WriteRequest;
import cast.v1.WriteResponse;
import com.google.protobuf.Any;
import com.google.protobuf.ByteString;
import com.google.protobuf.Timestamp;
import com.google.protobuf.UnsafeByteOperations;
import java.time.Duration;
import java.time.Instant;
import java.util.List;
import java.util.function.Function;

/**
 * Wire messages ({@code cast.v1}) to and from the library's types: the only place
 * besides the gRPC transport's own files that knows the generated classes, so that
 * none of them appears in the public API (the twin of
 * python/cast/client/conversions.py and cpp_client/src/conversions.cc).
 */
final class Conversions {
  private Conversions() {}

  // ------------------------------------------------------------- to the wire

  static EntryAddress address(String sa, String id) {
    return EntryAddress.newBuilder().setId(id).setSubarchitecture(sa).build();
  }

  /** A filter whose SA is known ("" for every SA); a local one must have been resolved first. */
  static cast.v1.ChangeFilter filter(ChangeFilter f) {
    if (f.isLocal()) {
      // The component fills in its own SA; reaching here without it would watch every SA.
      throw new IllegalArgumentException("a local filter must be given its SA before it is sent: " + f);
    }
    cast.v1.ChangeFilter.Builder b =
        cast.v1.ChangeFilter.newBuilder()
            .setType(f.type())
            .setId(f.id())
            .setSubarchitecture(f.subarchitecture())
            .setSourceComponent(f.sourceComponent())
            .setSourceSubarchitecture(f.sourceSubarchitecture())
            .setIncludeEntry(f.includeEntry());
    for (Operation op : f.operations()) {
      b.addOperations(operation(op));
    }
    return b.build();
  }

  /**
   * The wire constant of a library enum constant: the wire enums spell each library name
   * behind their own prefix (OVERWRITE is OPERATION_OVERWRITE, ODR is LOCK_MODE_ODR), so one
   * lookup serves them all; ConversionsTest maps every constant.
   */
  private static <W extends Enum<W>> W wire(Enum<?> value, Class<W> wireType, String prefix) {
    return Enum.valueOf(wireType, prefix + value.name());
  }

  static cast.v1.Operation operation(Operation op) {
    return wire(op, cast.v1.Operation.class, "OPERATION_");
  }

  static cast.v1.LockMode lockMode(LockMode mode) {
    return wire(mode, cast.v1.LockMode.class, "LOCK_MODE_");
  }

  static cast.v1.TaskOutcome outcome(TaskOutcome outcome) {
    return wire(outcome, cast.v1.TaskOutcome.class, "TASK_OUTCOME_");
  }

  static cast.v1.ComponentState state(ComponentState state) {
    return wire(state, cast.v1.ComponentState.class, "COMPONENT_STATE_");
  }

  static cast.v1.Delivery delivery(Delivery delivery) {
    return wire(delivery, cast.v1.Delivery.class, "DELIVERY_");
  }

  static AddRequest add(String sa, String id, Any value) {
    return add(sa, id, value, null);
  }

  /**
   * An add; with {@code staged} set its value's bytes are named in the staging area of the
   * shared-memory session, not carried (value keeps its type_url only).
   */
  static AddRequest add(String sa, String id, Any value, StagedValue staged) {
    var b = AddRequest.newBuilder().setAddress(address(sa, id));
    if (staged == null) {
      b.setValue(value);
    } else {
      b.setValue(typeOnly(value)).setStagedValue(staged);
    }
    return b.build();
  }

  /** An overwrite, checking the version unless {@code expectedVersion} is null. */
  static OverwriteRequest overwrite(String sa, String id, Any value, Long expectedVersion) {
    return overwrite(sa, id, value, expectedVersion, null);
  }

  /** An overwrite; {@code staged} as for {@link #add(String, String, Any, StagedValue)}. */
  static OverwriteRequest overwrite(String sa, String id, Any value, Long expectedVersion, StagedValue staged) {
    var b = OverwriteRequest.newBuilder().setAddress(address(sa, id));
    if (staged == null) {
      b.setValue(value);
    } else {
      b.setValue(typeOnly(value)).setStagedValue(staged);
    }
    if (expectedVersion != null) {
      b.setExpectedVersion(expectedVersion);
    }
    return b.build();
  }

  /** {@code value} without its bytes: what a request whose value is staged carries. */
  static Any typeOnly(Any value) {
    return Any.newBuilder().setTypeUrl(value.getTypeUrl()).build();
  }

  /** A delete, checking the version unless {@code expectedVersion} is null. */
  static DeleteRequest delete(String sa, String id, Long expectedVersion) {
    var b = DeleteRequest.newBuilder().setAddress(address(sa, id));
    if (expectedVersion != null) {
      b.setExpectedVersion(expectedVersion);
    }
    return b.build();
  }

  /** The writes of a batch, in order, all in {@code sa}. */
  static BatchRequest batch(String sa, List<Transport.Write> writes) {
    return batch(sa, writes, w -> null);
  }

  /** The writes of a batch; {@code staging} stages a write's value (null: its bytes go in the request). */
  static BatchRequest batch(String sa, List<Transport.Write> writes, Function<Any, StagedValue> staging) {
    BatchRequest.Builder req = BatchRequest.newBuilder();
    for (Transport.Write w : writes) {
      BatchOperation.Builder op = BatchOperation.newBuilder();
      switch (w.operation()) {
        case ADD -> op.setAdd(add(sa, w.id(), w.value(), staging.apply(w.value())));
        case OVERWRITE -> op.setOverwrite(
            overwrite(sa, w.id(), w.value(), w.expectedVersion(), staging.apply(w.value())));
        case DELETE -> op.setDelete(delete(sa, w.id(), w.expectedVersion()));
      }
      req.addOperations(op);
    }
    return req.build();
  }

  static LockRequest lock(String sa, String id, LockMode mode, boolean noWait) {
    return LockRequest.newBuilder().setAddress(address(sa, id)).setMode(lockMode(mode)).setNoWait(noWait).build();
  }

  // ------------------------------------------- requests of the Write stream

  /** Largest lock timeout the wire carries (timeout_ms is a uint32 of milliseconds). */
  static final long MAX_LOCK_TIMEOUT_MS = 0xFFFF_FFFFL;

  static WriteRequest.Builder writeAdd(String sa, String id, Any value) {
    return writeAdd(sa, id, value, null);
  }

  static WriteRequest.Builder writeAdd(String sa, String id, Any value, StagedValue staged) {
    return WriteRequest.newBuilder().setAdd(add(sa, id, value, staged));
  }

  static WriteRequest.Builder writeOverwrite(String sa, String id, Any value, Long expectedVersion) {
    return writeOverwrite(sa, id, value, expectedVersion, null);
  }

  static WriteRequest.Builder writeOverwrite(
      String sa, String id, Any value, Long expectedVersion, StagedValue staged) {
    return WriteRequest.newBuilder().setOverwrite(overwrite(sa, id, value, expectedVersion, staged));
  }

  static WriteRequest.Builder writeDelete(String sa, String id, Long expectedVersion) {
    return WriteRequest.newBuilder().setDelete(delete(sa, id, expectedVersion));
  }

  static WriteRequest.Builder writeBatch(String sa, List<Transport.Write> writes) {
    return writeBatch(sa, writes, w -> null);
  }

  static WriteRequest.Builder writeBatch(
      String sa, List<Transport.Write> writes, Function<Any, StagedValue> staging) {
    return WriteRequest.newBuilder().setBatch(batch(sa, writes, staging));
  }

  /**
   * A lock whose wait the server bounds by {@code timeout} (null, or {@code noWait}: no bound;
   * at least 1 ms, at most what the wire carries, about 49 days).
   */
  static WriteRequest.Builder writeLock(String sa, String id, LockMode mode, boolean noWait, Duration timeout) {
    long ms = noWait || timeout == null ? 0 : Math.min(Math.max(1, timeout.toMillis()), MAX_LOCK_TIMEOUT_MS);
    return WriteRequest.newBuilder().setLock(lock(sa, id, mode, noWait)).setTimeoutMs((int) ms);
  }

  static WriteRequest.Builder writeUnlock(String sa, String id) {
    return WriteRequest.newBuilder().setUnlock(UnlockRequest.newBuilder().setAddress(address(sa, id)));
  }

  static ProposeRequest propose(String name, Any data, int priority) {
    var b = ProposeRequest.newBuilder().setName(name).setPriority(priority);
    if (data != null) {
      b.setData(data);
    }
    return b.build();
  }

  static CompleteRequest complete(String taskId, TaskOutcome outcome, String reason) {
    return CompleteRequest.newBuilder()
        .setTaskId(taskId)
        .setOutcome(outcome(outcome))
        .setReason(reason == null ? "" : reason)
        .build();
  }

  // ----------------------------------------------------------- from the wire

  static WorkingMemoryAddress address(EntryAddress a) {
    return new WorkingMemoryAddress(a.getId(), a.getSubarchitecture());
  }

  static Instant time(Timestamp t) {
    return Instant.ofEpochSecond(t.getSeconds(), t.getNanos());
  }

  static WriteResult result(WriteResponse r) {
    return new WriteResult(r.getRevision(), r.getVersion());
  }

  static Transport.StoredEntry entry(cast.v1.Entry e) {
    return entry(e, null);
  }

  /**
   * An entry as read on {@code call} (null: a call that named no shared-memory session). One
   * whose value was lent by shared memory ({@code shared_value}) holds its lease, claimed on
   * that call, and wraps the lent bytes without copying them; UnavailableError when they cannot
   * be read (read again).
   */
  static Transport.StoredEntry entry(cast.v1.Entry e, SharedSession.ReadCall call) {
    Lease lease = null;
    ByteString value = e.getValue().getValue();
    if (e.hasSharedValue()) {
      if (call == null) {
        throw new UnavailableError(
            "entry '" + e.getAddress().getId() + "' came by shared memory on a call that named no session: read it"
                + " again");
      }
      lease = call.claim(e.getSharedValue());
      value = UnsafeByteOperations.unsafeWrap(lease.bytes());
    }
    return new Transport.StoredEntry(
        address(e.getAddress()),
        e.getType(),
        value,
        e.getVersion(),
        e.getAuthor(),
        e.getRevision(),
        time(e.getModified()),
        lease);
  }

  /** InvalidArgumentError for UNSPECIFIED or a value this library does not know. */
  static Operation operation(cast.v1.Operation op) {
    return switch (op) {
      case OPERATION_ADD -> Operation.ADD;
      case OPERATION_OVERWRITE -> Operation.OVERWRITE;
      case OPERATION_DELETE -> Operation.DELETE;
      default -> throw new InvalidArgumentError("unknown operation " + op + " in a change event");
    };
  }

  /** An event; InvalidArgumentError for one this library cannot represent (an unknown operation). */
  static Transport.Change change(cast.v1.ChangeEvent e) {
    return change(e, null);
  }

  /**
   * An event received on {@code call} (null: a stream that named no shared-memory session): its
   * entry as {@link #entry(cast.v1.Entry, SharedSession.ReadCall)} makes it. InvalidArgumentError
   * for one this library cannot represent (an unknown operation); UnavailableError when its lent
   * value cannot be read.
   */
  static Transport.Change change(cast.v1.ChangeEvent e, SharedSession.ReadCall call) {
    Operation operation = operation(e.getOperation()); // before the claim: a refusal leaves nothing lent
    return new Transport.Change(
        e.getRevision(),
        operation,
        address(e.getAddress()),
        e.getType(),
        e.getVersion(),
        e.getSourceComponent(),
        e.getSourceSubarchitecture(),
        time(e.getTime()),
        e.hasEntry() ? entry(e.getEntry(), call) : null,
        List.copyOf(e.getWatchIdsList()),
        e.getSkipped(),
        e.getFirstSkippedRevision());
  }

  static TaskState taskState(cast.v1.TaskState state) {
    return switch (state) {
      case TASK_STATE_WAITING -> TaskState.WAITING;
      case TASK_STATE_ADOPTED -> TaskState.ADOPTED;
      case TASK_STATE_REJECTED -> TaskState.REJECTED;
      case TASK_STATE_RETRACTED -> TaskState.RETRACTED;
      case TASK_STATE_COMPLETED -> TaskState.COMPLETED;
      default -> TaskState.UNSPECIFIED;
    };
  }

  static Task task(cast.v1.Task t) {
    return new Task(
        t.getTaskId(),
        t.getName(),
        t.getSubarchitecture(),
        t.getComponent(),
        t.getPriority(),
        taskState(t.getState()),
        t.getReason(),
        t.hasData() ? t.getData() : null);
  }

  /** Who the server says the caller is, verified from its token. */
  static Identity identity(RegisterResponse r) {
    return new Identity(r.getComponentId(), r.getSubarchitecture(), r.getPrivileged());
  }
}
