package cast.client;

/** Returned by {@code onChange}; {@link #cancel()} stops the callback. */
public final class WatchHandle {
  private final Dispatcher dispatcher;
  private final Transport transport;
  private final int watchId;
  private volatile CastError error;

  WatchHandle(Dispatcher dispatcher, Transport transport, int watchId) {
    this.dispatcher = dispatcher;
    this.transport = transport;
    this.watchId = watchId;
  }

  /** The watch id on the component's Watch streams. */
  public int watchId() {
    return watchId;
  }

  /** Whether the callback is still registered. */
  public boolean isActive() {
    return dispatcher.isRegistered(watchId);
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
    // Unregistered first: what is queued for it is dropped; the server is told once.
    if (dispatcher.unregister(watchId)) {
      transport.cancelWatch(watchId);
    }
  }

  @Override
  public String toString() {
    return "WatchHandle(" + watchId + (isActive() ? "" : ", cancelled") + ")";
  }
}
