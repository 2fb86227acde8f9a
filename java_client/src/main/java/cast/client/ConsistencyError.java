package cast.client;

/** The entry's version is not the expected one (ABORTED). */
public class ConsistencyError extends CastError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's (or the library's) message. */
  public ConsistencyError(String message) {
    super("ABORTED", message);
  }
}
