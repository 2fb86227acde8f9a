package cast.client;

import com.google.protobuf.Message;
import java.time.Instant;

/**
 * An entry read from a working memory: its value (a fresh object that nobody
 * else holds) and its metadata.
 *
 * @param <T> the entry's message class
 * @param address where the entry lives
 * @param type full protobuf name of the value's type
 * @param value the entry's value
 * @param version 0 after add, +1 with every overwrite
 * @param author id of the component that made the last write
 * @param revision the working memory's revision of the last write
 * @param modified server time of the last write
 */
public record Entry<T extends Message>(
    WorkingMemoryAddress address,
    String type,
    T value,
    long version,
    String author,
    long revision,
    Instant modified) {

  /** The entry's id. */
  public String id() {
    return address.id();
  }

  /** Decode a stored entry into {@code cls}; InvalidArgumentError if its type is another or its bytes do not parse. */
  static <T extends Message> Entry<T> decode(Transport.StoredEntry stored, Class<T> cls) {
    return decode(stored, cls, false);
  }

  /** As {@link #decode(Transport.StoredEntry, Class)}; {@code alias}: the value's bytes are a copy nobody else holds. */
  static <T extends Message> Entry<T> decode(Transport.StoredEntry stored, Class<T> cls, boolean alias) {
    T value = Types.decodeEntry(cls, stored, alias);
    return new Entry<>(
        stored.address(), stored.type(), value, stored.version(), stored.author(), stored.revision(), stored.modified());
  }
}
