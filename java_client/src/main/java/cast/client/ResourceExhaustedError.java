package cast.client;

/** A configured limit was reached (RESOURCE_EXHAUSTED). */
public class ResourceExhaustedError extends CastError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's (or the library's) message. */
  public ResourceExhaustedError(String message) {
    super("RESOURCE_EXHAUSTED", message);
  }
}
