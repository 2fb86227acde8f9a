package cast.client;

import com.google.protobuf.Any;
import java.lang.ref.Cleaner;
import java.nio.ByteBuffer;

/**
 * A large value written in place: the place of one top-level {@code bytes} field of a value, to
 * fill before writing it (Python: {@code cast.Loan}; C++: {@code cast::Loan}). {@link
 * Component#loan} takes it, for the value with every field set but that one; the loan is then
 * written instead of a message, by {@code add}, {@code overwrite}, {@code addAsync} or {@code
 * overwriteAsync} (not in a batch, which takes messages):
 *
 * <pre>
 * Frame frame = Frame.newBuilder().setWidth(640).setHeight(480).setEncoding("rgb8").build();
 * try (Loan loan = component.loan(frame, "pixels", 640 * 480 * 3)) {
 *   camera.grab(loan.buffer()); // fills the pixels where they are
 *   component.overwrite("camera", loan);
 * }
 * </pre>
 *
 * <p>On the server's host, for a value of at least the shared-memory threshold (64 KiB), the
 * buffer is in the component's staging area and the write names it there: nothing is copied on
 * the client ({@link #shared()} is true). Else (another host, shared memory off, a smaller value,
 * no room in the staging area) it is private memory and the write sends its bytes. Readers get the
 * same value either way.
 *
 * <p>A loan is written once; from then on (whatever the outcome) it is spent: {@link #buffer()}
 * throws InvalidArgumentError, a second write too, and buffers taken before must not be touched
 * (their memory may hold another value, or be gone). {@link #close()} gives an unwritten loan's
 * place back (try-with-resources); closing a written or closed loan does nothing. A loan never
 * closed nor written is given back when it is garbage, late: close loans you do not write. A loan
 * may be written from any thread, once.
 */
public final class Loan implements AutoCloseable {
  private final String subarchitecture;
  private final String typeUrl;
  private final LoanMemory memory;
  private final Cleaner.Cleanable cleanable;

  /** A loan for a value of {@code typeUrl} written to {@code subarchitecture}, in {@code memory}. */
  Loan(String subarchitecture, String typeUrl, LoanMemory memory) {
    this.subarchitecture = subarchitecture;
    this.typeUrl = typeUrl;
    this.memory = memory;
    // A loan dropped unwritten gives its place back, as a view never closed does (the leases' cleaner).
    this.cleanable = Lease.CLEANER.register(this, memory);
  }

  /**
   * The field's bytes, writable, in place: position 0, limit {@link #size()}, a new buffer at
   * each call (its position is the caller's). Their first contents are unspecified: fill them
   * all. InvalidArgumentError once the loan was written or closed.
   */
  public ByteBuffer buffer() {
    if (!memory.open()) {
      throw new InvalidArgumentError("this loan was written (or closed): its buffer is gone; take a new loan");
    }
    return memory.payload();
  }

  /** The field's size in bytes: what {@link #buffer()} holds. */
  public int size() {
    return memory.size;
  }

  /**
   * Whether the buffer is in the component's staging area in shared memory with the server, so
   * that the write copies nothing; false when it is private memory (the write sends bytes).
   */
  public boolean shared() {
    return memory.shared();
  }

  /** Give an unwritten loan's place back; nothing for a written or closed one. */
  @Override
  public void close() {
    cleanable.clean(); // runs memory.run() once, now, and never later
  }

  @Override
  public String toString() {
    return "Loan(" + Types.typeOf(Any.newBuilder().setTypeUrl(typeUrl).build()) + ", " + memory.size + " bytes in "
        + (memory.shared() ? "shared memory" : "private memory") + (memory.open() ? "" : ", spent") + ")";
  }

  // ------------------------------------------------------------ for the write

  /** The subarchitecture it was taken for. */
  String subarchitecture() {
    return subarchitecture;
  }

  /** The type URL of its value ({@code type.googleapis.com/} and the message's full name). */
  String typeUrl() {
    return typeUrl;
  }

  /** Where its value is (the write's, once {@link #spendFor} returned). */
  LoanMemory memory() {
    return memory;
  }

  /**
   * The loan is written to {@code sa} (resolved: never "" or null): from now on its memory is the
   * write's. InvalidArgumentError, the loan unchanged, when it was written or closed already, or
   * taken for another subarchitecture.
   */
  void spendFor(String sa) {
    if (!memory.open()) {
      throw spent();
    }
    if (!subarchitecture.equals(sa)) {
      throw new InvalidArgumentError(
          "the loan was taken for subarchitecture '" + subarchitecture + "' and is written to '" + sa
              + "': take it with subarchitecture '" + sa + "'");
    }
    if (!memory.spend()) { // another thread wrote or closed it meanwhile
      throw spent();
    }
    cleanable.clean(); // nothing left for the cleaner: the memory is spent
  }

  private static InvalidArgumentError spent() {
    return new InvalidArgumentError("this loan was already written (or closed): take a new loan for each write");
  }

  /**
   * Its value as bytes, header and payload, for a write that sends them (after {@link
   * #spendFor}); its place goes back.
   */
  Any value() {
    return Any.newBuilder().setTypeUrl(typeUrl).setValue(memory.bytes()).build();
  }
}
