package cast.client;

/** The component may not write where it tried to (PERMISSION_DENIED). */
public class PermissionDeniedError extends CastError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's (or the library's) message. */
  public PermissionDeniedError(String message) {
    super("PERMISSION_DENIED", message);
  }
}
