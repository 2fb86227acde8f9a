package cast.client;

/** The entry, subarchitecture or task does not exist (NOT_FOUND). */
public class NotFoundError extends CastError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's (or the library's) message. */
  public NotFoundError(String message) {
    super("NOT_FOUND", message);
  }
}
