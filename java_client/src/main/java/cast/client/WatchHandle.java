package cast.client;

/** Returned by {@code onChange}; {@link #cancel()} stops the callback. */
public final class WatchHandle {
  private final Component component;
  private final int watchId;
  private volatile CastError error;

  WatchHandle(Component component, int watchId) {
    this.component = component;
    this.watchId = watchId;
  }

  /** The watch id on the component's Watch streams. */
  public int watchId() {
    return watchId;
  }

  /** Whether the callback is still registered. */
  public boolean isActive() {
    return component.hasWatch(watchId);
  }

  /** Why delivery stopped (e.g. HistoryExpiredError), or null while it goes on. */
  public CastError error() {
    return error;
  }

  void setError(CastError error) {
    this.error = error;
  }

  /**
   * Stop delivering changes to this callback (idempotent). Changes already queued
   * for it and not yet delivered are dropped.
   */
  public void cancel() {
    component.cancelWatch(watchId);
  }

  @Override
  public String toString() {
    return "WatchHandle(" + watchId + (isActive() ? "" : ", cancelled") + ")";
  }
}
