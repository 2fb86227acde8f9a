package cast.client;

/** A bug: the server failed in a way it should not (INTERNAL). */
public class InternalError extends CastError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's (or the library's) message. */
  public InternalError(String message) {
    super("INTERNAL", message);
  }
}
