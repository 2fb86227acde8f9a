package cast.client;

/**
 * A schema file registered again with other types (FAILED_PRECONDITION). The server names it in
 * the {@code cast-error} trailer; a {@code catch (LockedError e)} still catches it.
 */
public class SchemaConflictError extends LockedError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's message. */
  public SchemaConflictError(String message) {
    super(message);
  }
}
