package cast.client;

/** Another component holds a lock that forbids this; also an unlock of an entry the caller does not hold (FAILED_PRECONDITION). */
public class LockedError extends CastError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's (or the library's) message. */
  public LockedError(String message) {
    super("FAILED_PRECONDITION", message);
  }
}
