package cast.client;

import com.google.protobuf.Message;
import java.nio.ByteBuffer;
import java.time.Instant;

/**
 * An entry's value, serialised, as a read-only {@link ByteBuffer} that is not a copy, with the
 * entry's metadata as {@link Entry} has it (Python: {@code cast.ValueView}; C++: {@code
 * cast::ValueView}). {@link Component#getView} and {@link WorkingMemoryChange#view()} make
 * them: on the server's host a large value is the server's shared memory, lent to this
 * component while the view is open (nothing is copied, however large); elsewhere, or for a
 * small value, the bytes received. {@link #field(int)} is the bytes of one top-level field (an
 * image's pixels in a {@code bytes} field), still not copied:
 *
 * <pre>
 * try (ValueView view = component.getView("camera")) {
 *   ByteBuffer pixels = view.field(1);
 *   ... read pixels ...
 * }
 * </pre>
 *
 * <p>The bytes never change while the view is open. {@link #close()} (or {@link #release()})
 * gives the value back; buffers taken from the view must not be read after that (the server
 * may put another value in their place), and its methods throw InvalidArgumentError. A view
 * never closed is given back when it is garbage, late. A view is safe to use from any thread.
 */
public final class ValueView implements AutoCloseable {
  private final Transport.StoredEntry entry;
  private final Lease lease; // null: the bytes were received, not lent
  private volatile boolean released;

  /** The view of {@code entry}, taking over one holder of its lease (if it was lent). */
  ValueView(Transport.StoredEntry entry) {
    this.entry = entry;
    this.lease = entry.lease();
  }

  private Transport.StoredEntry held() {
    if (released) {
      throw new InvalidArgumentError(
          "this view of entry '" + entry.address().id() + "' in subarchitecture '" + entry.address().subarchitecture()
              + "' was released: read the entry again");
    }
    return entry;
  }

  /** Where the entry lives. */
  public WorkingMemoryAddress address() {
    return held().address();
  }

  /** The entry's id. */
  public String id() {
    return held().address().id();
  }

  /** The full message name of the value. */
  public String type() {
    return held().type();
  }

  /** The entry's version this value is of. */
  public long version() {
    return held().version();
  }

  /** The component that wrote it. */
  public String author() {
    return held().author();
  }

  /** The working memory's revision of the write. */
  public long revision() {
    return held().revision();
  }

  /** When it was written (server clock). */
  public Instant modified() {
    return held().modified();
  }

  /** Whether the bytes are the server's shared memory (lent on its host), not a received copy. */
  public boolean isShared() {
    held();
    return lease != null;
  }

  /** The size of the serialised value in bytes. */
  public int size() {
    return held().value().size();
  }

  /** The serialised value, read-only, from position 0 (a new buffer each call: its position is the caller's). */
  public ByteBuffer data() {
    return held().value().asReadOnlyByteBuffer();
  }

  /**
   * The bytes of top-level field {@code number} (a {@code bytes}, string or message field),
   * read-only, not copied; empty when the field is absent (the last occurrence wins, as when
   * protobuf parses). InvalidArgumentError for a field of another kind (a number) or bytes
   * that are not a serialised message.
   */
  public ByteBuffer field(int number) {
    Transport.StoredEntry e = held();
    return fieldOf(
        e.value().asReadOnlyByteBuffer(),
        number,
        "entry '" + e.address().id() + "' in subarchitecture '" + e.address().subarchitecture() + "'");
  }

  /** The value as a {@code cls} message (a copy, as {@link Component#get} gives). */
  public <T extends Message> T decode(Class<T> cls) {
    return Types.decodeEntry(cls, held());
  }

  /** Give the value back; buffers taken from the view must not be read any more. Idempotent. */
  public void release() {
    if (released) {
      return;
    }
    released = true;
    if (lease != null) {
      lease.release();
    }
  }

  /** {@link #release()}: a view is used in try-with-resources. */
  @Override
  public void close() {
    release();
  }

  @Override
  public String toString() {
    if (released) {
      return "ValueView(released)";
    }
    return "ValueView(" + entry.address() + " type=" + entry.type() + " v=" + entry.version() + " "
        + entry.value().size() + " bytes in " + (lease != null ? "shared memory" : "bytes") + ")";
  }

  // ------------------------------------------------------------ the wire format

  private static long varint(ByteBuffer data, String what) {
    long value = 0;
    for (int shift = 0; ; shift += 7) {
      if (!data.hasRemaining() || shift > 63) {
        throw new InvalidArgumentError(what + ": the value ends inside a varint: it is not a serialised message");
      }
      byte b = data.get();
      value |= (long) (b & 0x7F) << shift;
      if (b >= 0) {
        return value;
      }
    }
  }

  /**
   * The bytes of top-level field {@code number} of the serialised message {@code data}
   * (from its position to its limit), not copied; {@code what} names the value in errors.
   */
  static ByteBuffer fieldOf(ByteBuffer data, int number, String what) {
    ByteBuffer in = data.slice();
    ByteBuffer found = in.slice(0, 0);
    while (in.hasRemaining()) {
      long key = varint(in, what);
      long tag = key >>> 3;
      int kind = (int) (key & 7);
      long skip;
      switch (kind) {
        case 0 -> {
          varint(in, what);
          skip = 0;
        }
        case 1 -> skip = 8;
        case 5 -> skip = 4;
        case 2 -> skip = varint(in, what);
        default -> throw new InvalidArgumentError(
            what + ": field " + tag + " has wire type " + kind + ", which a view does not read");
      }
      if (tag == number && kind != 2) {
        throw new InvalidArgumentError(what + ": field " + number + " is a number, not bytes, a string or a message");
      }
      if (skip < 0 || skip > in.remaining()) {
        throw new InvalidArgumentError(what + ": field " + tag + " runs past the end: it is not a serialised message");
      }
      if (tag == number) {
        found = in.slice(in.position(), (int) skip);
      }
      in.position(in.position() + (int) skip);
    }
    return found.asReadOnlyBuffer();
  }
}
