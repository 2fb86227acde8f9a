package cast.client;

/** The server cannot be reached (UNAVAILABLE). */
public class UnavailableError extends CastError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's (or the library's) message. */
  public UnavailableError(String message) {
    super("UNAVAILABLE", message);
  }
}
