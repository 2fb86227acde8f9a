package cast.client;

/** The call had no valid token (UNAUTHENTICATED). */
public class UnauthenticatedError extends CastError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's (or the library's) message. */
  public UnauthenticatedError(String message) {
    super("UNAUTHENTICATED", message);
  }
}
