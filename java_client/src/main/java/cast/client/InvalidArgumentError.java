package cast.client;

/** A bad id, type, value or request (INVALID_ARGUMENT). */
public class InvalidArgumentError extends CastError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's (or the library's) message. */
  public InvalidArgumentError(String message) {
    super("INVALID_ARGUMENT", message);
  }
}
