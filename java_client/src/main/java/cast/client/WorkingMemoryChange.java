package cast.client;

import com.google.protobuf.ByteString;
import com.google.protobuf.Message;
import java.time.Instant;

/** One change event as delivered to an {@code onChange} callback. */
public final class WorkingMemoryChange {
  private final Transport.Change change;
  // A value lent by shared memory, copied to the heap (read, or its callback returned); guarded by this.
  private Transport.StoredEntry copy;
  private boolean viewed; // the callback took a view: no copy is made; guarded by this

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
   * object, during the callback or at any time after it. A large value that came by shared
   * memory is copied out of it once, the first time it is read here or, if the callback did not
   * read it, when the callback returns; unless the callback took a {@link #view()}: then the
   * value is read through the view after the callback, and this throws InvalidArgumentError.
   */
  public <T extends Message> Entry<T> entry(Class<T> cls) {
    Transport.StoredEntry e = entryOrFail();
    if (e.lease() == null) {
      return Entry.decode(e, cls);
    }
    return Entry.decode(copied(e), cls, true); // the copy is this change's alone: the message may share it
  }

  /**
   * The value the event carries, serialised, as a read-only buffer that is not a copy
   * ({@link ValueView}): on the server's host a large value is the server's shared memory, lent
   * while the view is open, also after the callback returned; elsewhere the bytes received.
   * Take it during the callback, and close it when done.
   */
  public ValueView view() {
    Transport.StoredEntry e = entryOrFail();
    if (e.lease() == null) {
      return new ValueView(e);
    }
    synchronized (this) {
      viewed = true; // no copy when the callback returns
    }
    if (e.retain()) {
      return new ValueView(e);
    }
    synchronized (this) {
      if (copy != null) {
        return new ValueView(copy); // after the callback, which did not view it: its copy
      }
    }
    throw gone();
  }

  private Transport.StoredEntry entryOrFail() {
    Transport.StoredEntry e = change.entry();
    if (e == null) {
      throw new InvalidArgumentError("this change carries no entry: ask for it with filter.withEntry()");
    }
    return e;
  }

  private InvalidArgumentError gone() {
    return new InvalidArgumentError(
        "the value of " + this + " came by shared memory, its callback took a view() of it and returned: read it"
            + " through that view");
  }

  /** The lent entry {@code e} with its value copied to the heap (once; the lease must still be held). */
  private synchronized Transport.StoredEntry copied(Transport.StoredEntry e) {
    if (copy == null) {
      if (!e.retain()) {
        throw gone();
      }
      try {
        copy = new Transport.StoredEntry(e.address(), e.type(), ByteString.copyFrom(e.value().asReadOnlyByteBuffer()),
            e.version(), e.author(), e.revision(), e.modified());
      } finally {
        e.release();
      }
    }
    return copy;
  }

  /**
   * The callback returned (the dispatcher then lets go of its hold of a lent value): a value the
   * callback neither read nor viewed is copied now, so that the change can be read later.
   */
  void callbackReturned() {
    Transport.StoredEntry e = change.entry();
    synchronized (this) {
      if (e == null || e.lease() == null || copy != null || viewed) {
        return;
      }
    }
    copied(e);
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
