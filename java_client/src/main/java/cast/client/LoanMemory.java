package cast.client;

import com.google.protobuf.ByteString;
import com.google.protobuf.UnsafeByteOperations;
import java.nio.ByteBuffer;
import java.util.concurrent.atomic.AtomicInteger;

/**
 * Where a {@link Loan}'s value is, and whether it is still the loan's. The value is an ordinary
 * serialised message: its header (the other fields, then the loaned field's key and length, made
 * by {@link LoanHeader}), then its payload (the field's bytes: the loan's buffer). Either {@link
 * InStaging}, a region of a shared-memory session's staging area (the write names it, nothing
 * copied), or {@link InHeap}, private memory (the write sends its bytes).
 *
 * <p>A loan is open until it is written ({@link #spend}: from then on its memory is the write's,
 * which names it or sends its bytes and then gives it back) or closed ({@link #run}: its place goes
 * back). {@link #run} is also what the loan's cleaner runs when an open loan became garbage: so
 * this object never refers to the loan.
 */
abstract class LoanMemory implements Runnable {
  private static final int OPEN = 0;
  private static final int SPENT = 1;
  private static final int CLOSED = 2;

  private final AtomicInteger state = new AtomicInteger(OPEN);
  /** The payload's size in bytes. */
  final int size;

  private LoanMemory(int size) {
    this.size = size;
  }

  /**
   * The memory for a loan of {@code size} bytes after {@code header}: in {@code session}'s staging
   * area when there is a session (null: none), the value is at least its threshold and there is
   * room; else private memory.
   */
  static LoanMemory of(SharedSession session, ByteString header, int size) {
    if (session != null && (long) header.size() + size >= session.threshold) {
      ShmStaging.Lent lent = session.lend(header, size);
      if (lent != null) {
        return new InStaging(session, lent, size);
      }
    }
    return new InHeap(header, size);
  }

  /** The payload's place, writable, from position 0 to {@link #size}: a new buffer each call. */
  abstract ByteBuffer payload();

  /** Whether the payload is in a staging area (a write in its session copies nothing). */
  abstract boolean shared();

  /**
   * The value's bytes, header and payload, for a write that sends them (once, after {@link
   * #spend}); its place goes back.
   */
  abstract ByteString bytes();

  /** The value's place goes back: the loan was closed, or its write sent nothing. */
  abstract void giveBack();

  /** Whether the loan is neither written nor closed. */
  final boolean open() {
    return state.get() == OPEN;
  }

  /** The loan is being written: true once, if it was open; the memory is the write's from then on. */
  final boolean spend() {
    return state.compareAndSet(OPEN, SPENT);
  }

  /** Close the loan: an open one gives its place back; a written or closed one nothing. */
  @Override
  public final void run() {
    if (state.compareAndSet(OPEN, CLOSED)) {
      giveBack();
    }
  }

  /** A loan's value in private memory: an array the write sends as it is. */
  static final class InHeap extends LoanMemory {
    private final byte[] value;
    private final int header;

    InHeap(ByteString header, int size) {
      super(size);
      this.header = header.size();
      this.value = new byte[header.size() + size];
      header.copyTo(value, 0);
    }

    @Override
    ByteBuffer payload() {
      return ByteBuffer.wrap(value, header, size).slice();
    }

    @Override
    boolean shared() {
      return false;
    }

    @Override
    ByteString bytes() {
      // The array is the write's now (the buffer is not touched after it): wrapped, not copied.
      return UnsafeByteOperations.unsafeWrap(value);
    }

    @Override
    void giveBack() {} // the collector takes the array
  }

  /** A loan's value in a region of a session's staging area, lent by {@link ShmStaging#lend}. */
  static final class InStaging extends LoanMemory {
    final SharedSession session;
    final ShmStaging.Lent lent;

    InStaging(SharedSession session, ShmStaging.Lent lent, int size) {
      super(size);
      this.session = session;
      this.lent = lent;
    }

    @Override
    ByteBuffer payload() {
      return lent.payload().duplicate();
    }

    @Override
    boolean shared() {
      return true;
    }

    /** Whether the value can be named where it is by a write staged in {@code writer}: its session, still live. */
    boolean in(SharedSession writer) {
      return session == writer && writer.dead() == null;
    }

    /** The region is the write's now: it names it, and frees or keeps it after the reply as a staged value's. */
    ShmStaging.Lent handOver() {
      session.staging().handOver(lent);
      return lent;
    }

    @Override
    ByteString bytes() {
      // Another session takes the write (a renewed token), or none: the bytes go, copied out of this one.
      ByteString bytes = session.staging().copy(lent);
      giveBack();
      return bytes;
    }

    @Override
    void giveBack() {
      session.staging().giveBack(lent);
    }
  }
}
