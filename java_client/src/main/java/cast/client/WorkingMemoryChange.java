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

  /**
   * The entry carried by the event (after the write; for DELETE, as it was), its value a new
   * object. A value that came by shared memory is read during the callback: after the
   * callback returned it was given back, and this throws InvalidArgumentError (keep a {@link
   * #view()} to hold it longer).
   */
  public <T extends Message> Entry<T> entry(Class<T> cls) {
    Transport.StoredEntry e = held();
    try {
      return Entry.decode(e, cls);
    } finally {
      e.release();
    }
  }

  /**
   * The value the event carries, serialised, as a read-only buffer that is not a copy
   * ({@link ValueView}): on the server's host a large value is the server's shared memory, lent
   * while the view is open, also after the callback returned; elsewhere the bytes received.
   * Take it during the callback, and close it when done.
   */
  public ValueView view() {
    return new ValueView(held());
  }

  /** The entry, with one more holder of its value (the caller lets go of it). */
  private Transport.StoredEntry held() {
    Transport.StoredEntry e = change.entry();
    if (e == null) {
      throw new InvalidArgumentError("this change carries no entry: ask for it with filter.withEntry()");
    }
    if (!e.retain()) {
      throw new InvalidArgumentError(
          "the value of " + this + " came by shared memory and was given back when its callback returned: read"
              + " it in the callback (entry(cls)), or keep a view() of it");
    }
    return e;
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
