package cast.client;

/**
 * A task call its task's state does not allow, e.g. completing a task that is still waiting
 * (FAILED_PRECONDITION). The server names it in the {@code cast-error} trailer; a
 * {@code catch (LockedError e)} still catches it.
 */
public class TaskStateError extends LockedError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's message. */
  public TaskStateError(String message) {
    super(message);
  }
}
