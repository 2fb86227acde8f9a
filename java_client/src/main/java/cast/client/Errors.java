package cast.client;

import io.grpc.Metadata;
import io.grpc.Status;
import java.util.Map;
import java.util.function.Function;

/**
 * Maps gRPC status codes to the named CAST errors (docs/client-protocol.md,
 * "Errors"), the same table in every client library.
 */
final class Errors {
  private Errors() {}

  /**
   * The trailing metadata key in which the server names the error's class when several share its
   * status code ("TaskStateError" next to FAILED_PRECONDITION).
   */
  public static final String ERROR_TRAILER = "cast-error";

  private static final Metadata.Key<String> ERROR_TRAILER_KEY =
      Metadata.Key.of(ERROR_TRAILER, Metadata.ASCII_STRING_MARSHALLER);

  /** A class the trailer may name, with the status code it refines. */
  private record Precise(String code, Function<String, CastError> make) {}

  /** The classes the trailer may name (Python's errors._BY_NAME). */
  private static final Map<String, Precise> BY_NAME =
      Map.of(
          "TaskStateError", new Precise("FAILED_PRECONDITION", TaskStateError::new),
          "NoSessionError", new Precise("FAILED_PRECONDITION", NoSessionError::new),
          "SchemaConflictError", new Precise("FAILED_PRECONDITION", SchemaConflictError::new));

  /** The named error for a status code name ("NOT_FOUND", ...); CastError for any other code. */
  public static CastError forCode(String codeName, String message) {
    return forCode(codeName, message, null);
  }

  /**
   * The named error for a status code name, made precise by {@code errorName} (the {@link
   * #ERROR_TRAILER} trailer, null for none): TaskStateError for FAILED_PRECONDITION, for instance.
   * An unknown name, or a name of another code, is ignored, as in Python's {@code error_for_code}.
   */
  public static CastError forCode(String codeName, String message, String errorName) {
    String msg = message == null || message.isEmpty() ? codeName : message;
    Precise precise = errorName == null ? null : BY_NAME.get(errorName);
    if (precise != null && precise.code().equals(codeName)) {
      return precise.make().apply(msg);
    }
    switch (codeName) {
      case "ALREADY_EXISTS":
        return new AlreadyExistsError(msg);
      case "NOT_FOUND":
        return new NotFoundError(msg);
      case "ABORTED":
        return new ConsistencyError(msg);
      case "PERMISSION_DENIED":
        return new PermissionDeniedError(msg);
      case "FAILED_PRECONDITION":
        return new LockedError(msg);
      case "INVALID_ARGUMENT":
        return new InvalidArgumentError(msg);
      case "UNAUTHENTICATED":
        return new UnauthenticatedError(msg);
      case "DEADLINE_EXCEEDED":
        return new DeadlineExceededError(msg);
      case "OUT_OF_RANGE":
        return new HistoryExpiredError(msg);
      case "RESOURCE_EXHAUSTED":
        return new ResourceExhaustedError(msg);
      case "UNAVAILABLE":
        return new UnavailableError(msg);
      case "INTERNAL":
        return new InternalError(msg);
      default:
        return new CastError(codeName, msg);
    }
  }

  /** The named error for a gRPC status. */
  public static CastError fromStatus(Status status) {
    return fromStatus(status, null);
  }

  /** The class the server named in a call's trailing metadata ({@link #ERROR_TRAILER}), or null. */
  public static String errorName(Metadata trailers) {
    return trailers == null ? null : trailers.get(ERROR_TRAILER_KEY);
  }

  /** The named error for a gRPC status and the call's trailing metadata (null for none). */
  public static CastError fromStatus(Status status, Metadata trailers) {
    String name = status.getCode().name();
    String details = status.getDescription();
    if (details == null || details.isEmpty()) {
      details = status.getCause() != null ? String.valueOf(status.getCause()) : name;
    }
    if (status.getCode() == Status.Code.UNAVAILABLE) {
      // Say which side failed (the details alone, "io exception", do not) and what to do.
      return new UnavailableError(
          "server unavailable ("
              + details
              + "): a write made by this call may or may not have been applied; the client reconnects by"
              + " itself, retry the call later");
    }
    return forCode(name, details, errorName(trailers));
  }

  /**
   * The named error for a failure of a gRPC call: a status exception becomes its
   * CAST error (the precise one its trailers name); a CastError passes unchanged;
   * anything else becomes CastError.
   */
  public static CastError fromThrowable(Throwable t) {
    if (t instanceof CastError) {
      return (CastError) t;
    }
    return fromStatus(Status.fromThrowable(t), Status.trailersFromThrowable(t));
  }
}
