package cast.client;

import com.google.protobuf.Message;
import java.util.ArrayList;
import java.util.List;

/**
 * Many writes to one SA's working memory applied in order, all or nothing, in one
 * call: {@code batch().add(a, x).overwrite(b, y).deleteEntry(c).apply()}. If one
 * fails none is applied, and the error names the failing operation's index. A batch takes
 * messages only: a {@link Loan} is written with {@code add} or {@code overwrite} of the component.
 */
public final class Batch {
  private final Component component;
  private final String subarchitecture;
  private final List<Transport.Write> writes = new ArrayList<>();

  Batch(Component component, String subarchitecture) {
    this.component = component;
    this.subarchitecture = subarchitecture;
  }

  /** Add an entry. */
  public Batch add(String id, Message value) {
    writes.add(new Transport.Write(Operation.ADD, id, component.serialise(value, subarchitecture), null));
    return this;
  }

  /** Overwrite an entry. */
  public Batch overwrite(String id, Message value) {
    return overwrite(id, value, null);
  }

  /** Overwrite an entry if its version is {@code expectedVersion} (null: any version). */
  public Batch overwrite(String id, Message value, Long expectedVersion) {
    writes.add(new Transport.Write(Operation.OVERWRITE, id, component.serialise(value, subarchitecture), expectedVersion));
    return this;
  }

  /** Delete an entry. */
  public Batch deleteEntry(String id) {
    return deleteEntry(id, null);
  }

  /** Delete an entry if its version is {@code expectedVersion} (null: any version). */
  public Batch deleteEntry(String id, Long expectedVersion) {
    writes.add(new Transport.Write(Operation.DELETE, id, null, expectedVersion));
    return this;
  }

  /** How many writes are queued. */
  public int size() {
    return writes.size();
  }

  /** Apply the writes; one result per write, in order. */
  public List<WriteResult> apply() {
    if (writes.isEmpty()) {
      return List.of();
    }
    return component.applyBatch(subarchitecture, List.copyOf(writes));
  }
}
