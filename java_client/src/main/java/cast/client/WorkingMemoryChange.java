package cast.client;

import com.google.protobuf.Message;
import java.time.Instant;

/** One change event as delivered to an {@code onChange} callback. */
public final class WorkingMemoryChange {
  private final Transport.Change change;

  WorkingMemoryChange(Transport.Change change) {
    this.change = change;
  }

  /** ADD, OVERWRITE or DELETE. */
  public Operation operation() {
    return change.operation();
  }

  /** The working memory's revision of the change (1, 2, 3, ... per SA). */
  public long revision() {
    return change.revision();
  }

  /** Full message name of the entry's value. */
  public String type() {
    return change.type();
  }

  /** The entry's version after the change (for DELETE: the version it had). */
  public long version() {
    return change.version();
  }

  /** Id of the component that made the change. */
  public String sourceComponent() {
    return change.sourceComponent();
  }

  /** SA of the component that made the change. */
  public String sourceSubarchitecture() {
    return change.sourceSubarchitecture();
  }

  /** Server time of the change. */
  public Instant time() {
    return change.time();
  }

  /** The entry changed. */
  public WorkingMemoryAddress address() {
    return change.address();
  }

  /** The changed entry's id. */
  public String id() {
    return change.address().id();
  }

  /** The SA whose working memory changed. */
  public String subarchitecture() {
    return change.address().subarchitecture();
  }

  /**
   * How many earlier changes of this entry a {@link Delivery#LATEST} watch did not receive
   * because this newer one replaced them (on the server or in the component's queue); 0
   * when none, and always 0 for a QUEUE watch.
   */
  public long skipped() {
    return change.skipped();
  }

  /** The revision of the oldest change {@link #skipped()} counts (0 when none): they lie between it and this one. */
  public long firstSkippedRevision() {
    return change.firstSkippedRevision();
  }

  /** Whether the event carries the entry (its filter asked for it with {@code withEntry()}). */
  public boolean hasEntry() {
    return change.entry() != null;
  }

  /** The entry carried by the event (after the write; for DELETE, as it was). */
  public <T extends Message> Entry<T> entry(Class<T> cls) {
    if (change.entry() == null) {
      throw new InvalidArgumentError("this change carries no entry: ask for it with filter.withEntry()");
    }
    return Entry.decode(change.entry(), cls);
  }

  @Override
  public String toString() {
    return "WorkingMemoryChange("
        + operation()
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
        + (skipped() == 0 ? "" : " skipped=" + skipped() + " from rev " + firstSkippedRevision())
        + ")";
  }
}
