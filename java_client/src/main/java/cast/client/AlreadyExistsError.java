package cast.client;

/** An entry with this id already exists (ALREADY_EXISTS). */
public class AlreadyExistsError extends CastError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's (or the library's) message. */
  public AlreadyExistsError(String message) {
    super("ALREADY_EXISTS", message);
  }
}
