package cast.client;

/** The call's deadline passed before it could complete (DEADLINE_EXCEEDED). */
public class DeadlineExceededError extends CastError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's (or the library's) message. */
  public DeadlineExceededError(String message) {
    super("DEADLINE_EXCEEDED", message);
  }
}
