package cast.client;

import com.google.protobuf.Message;
import java.time.Instant;

/** One change event as delivered to an {@code onChange} callback. */
public final class WorkingMemoryChange {
  private final cast.v1.ChangeEvent event;
  private final Operation operation;

  WorkingMemoryChange(cast.v1.ChangeEvent event) {
    this.event = event;
    this.operation = Operation.fromProto(event.getOperation());
  }

  /** ADD, OVERWRITE or DELETE. */
  public Operation operation() {
    return operation;
  }

  /** The working memory's revision of the change (1, 2, 3, ... per SA). */
  public long revision() {
    return event.getRevision();
  }

  /** Full message name of the entry's value. */
  public String type() {
    return event.getType();
  }

  /** The entry's version after the change (for DELETE: the version it had). */
  public long version() {
    return event.getVersion();
  }

  /** Id of the component that made the change. */
  public String sourceComponent() {
    return event.getSourceComponent();
  }

  /** SA of the component that made the change. */
  public String sourceSubarchitecture() {
    return event.getSourceSubarchitecture();
  }

  /** Server time of the change. */
  public Instant time() {
    return Instant.ofEpochSecond(event.getTime().getSeconds(), event.getTime().getNanos());
  }

  /** The entry changed. */
  public WorkingMemoryAddress address() {
    return new WorkingMemoryAddress(event.getAddress().getId(), event.getAddress().getSubarchitecture());
  }

  /** The changed entry's id. */
  public String id() {
    return event.getAddress().getId();
  }

  /** The SA whose working memory changed. */
  public String subarchitecture() {
    return event.getAddress().getSubarchitecture();
  }

  /** Whether the event carries the entry (its filter asked for it with {@code withEntry()}). */
  public boolean hasEntry() {
    return event.hasEntry();
  }

  /** The entry carried by the event (after the write; for DELETE, as it was). */
  public <T extends Message> Entry<T> entry(Class<T> cls) {
    if (!event.hasEntry()) {
      throw new InvalidArgumentError("this change carries no entry: ask for it with filter.withEntry()");
    }
    return Entry.fromProto(event.getEntry(), cls);
  }

  /** The wire event (a copy is not needed: protobuf messages are immutable). */
  public cast.v1.ChangeEvent toProto() {
    return event;
  }

  @Override
  public String toString() {
    return "WorkingMemoryChange("
        + operation
        + " "
        + address()
        + " type="
        + type()
        + " v="
        + version()
        + " rev="
        + revision()
        + " by="
        + sourceComponent()
        + ")";
  }
}
