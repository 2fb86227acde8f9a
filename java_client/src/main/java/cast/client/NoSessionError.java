package cast.client;

/**
 * A lock or a task asked for by a component with no live session (FAILED_PRECONDITION): locks
 * and tasks end with the session that took them, so without one nothing would release them.
 * The server names it in the {@code cast-error} trailer; a {@code catch (LockedError e)} still
 * catches it.
 */
public class NoSessionError extends LockedError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's message. */
  public NoSessionError(String message) {
    super(message);
  }
}
