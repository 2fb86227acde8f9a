package cast.client;

/**
 * Base class of every CAST error. {@link #code()} is the gRPC status code name
 * ("NOT_FOUND", ...), the same as Python's {@code CastError.code}; the message is
 * the server's status details, unchanged.
 *
 * <p>Unchecked, like every error of the component API: components let most of
 * them propagate and catch the few they expect ({@link LockedError}, ...).
 */
public class CastError extends RuntimeException {
  private static final long serialVersionUID = 1L;
  private final String code;

  /** An error with the given gRPC status code name. */
  public CastError(String code, String message) {
    super(message);
    this.code = code;
  }

  /** An error of unknown kind (code UNKNOWN). */
  public CastError(String message) {
    this("UNKNOWN", message);
  }

  /** The gRPC status code name of this error. */
  public String code() {
    return code;
  }
}
