package cast.client;

import cast.v1.AddRequest;
import cast.v1.BatchOperation;
import cast.v1.BatchRequest;
import cast.v1.DeleteRequest;
import cast.v1.OverwriteRequest;
import com.google.protobuf.Message;
import java.util.List;

/**
 * Many writes to one SA's working memory applied in order, all or nothing, in one
 * call: {@code batch().add(a, x).overwrite(b, y).deleteEntry(c).apply()}. If one
 * fails none is applied, and the error names the failing operation's index.
 */
public final class Batch {
  private final Component component;
  private final String subarchitecture;
  private final BatchRequest.Builder request = BatchRequest.newBuilder();

  Batch(Component component, String subarchitecture) {
    this.component = component;
    this.subarchitecture = subarchitecture;
  }

  private cast.v1.EntryAddress addr(String id) {
    return new WorkingMemoryAddress(id, subarchitecture).toProto();
  }

  /** Add an entry. */
  public Batch add(String id, Message value) {
    request.addOperations(
        BatchOperation.newBuilder()
            .setAdd(AddRequest.newBuilder().setAddress(addr(id)).setValue(component.serialise(value))));
    return this;
  }

  /** Overwrite an entry. */
  public Batch overwrite(String id, Message value) {
    return overwrite(id, value, null);
  }

  /** Overwrite an entry if its version is {@code expectedVersion} (null: any version). */
  public Batch overwrite(String id, Message value, Long expectedVersion) {
    var b = OverwriteRequest.newBuilder().setAddress(addr(id)).setValue(component.serialise(value));
    if (expectedVersion != null) {
      b.setExpectedVersion(expectedVersion);
    }
    request.addOperations(BatchOperation.newBuilder().setOverwrite(b));
    return this;
  }

  /** Delete an entry. */
  public Batch deleteEntry(String id) {
    return deleteEntry(id, null);
  }

  /** Delete an entry if its version is {@code expectedVersion} (null: any version). */
  public Batch deleteEntry(String id, Long expectedVersion) {
    var b = DeleteRequest.newBuilder().setAddress(addr(id));
    if (expectedVersion != null) {
      b.setExpectedVersion(expectedVersion);
    }
    request.addOperations(BatchOperation.newBuilder().setDelete(b));
    return this;
  }

  /** How many writes are queued. */
  public int size() {
    return request.getOperationsCount();
  }

  /** Apply the writes; one result per write, in order. */
  public List<WriteResult> apply() {
    if (request.getOperationsCount() == 0) {
      return List.of();
    }
    return component.applyBatch(subarchitecture, request.build());
  }
}
