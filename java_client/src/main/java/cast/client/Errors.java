package cast.client;

import io.grpc.Status;
import io.grpc.StatusException;
import io.grpc.StatusRuntimeException;

/**
 * Maps gRPC status codes to the named CAST errors (docs/client-protocol.md,
 * "Errors"), the same table in every client library.
 */
public final class Errors {
  private Errors() {}

  /** The named error for a status code name ("NOT_FOUND", ...); CastError for any other code. */
  public static CastError forCode(String codeName, String message) {
    String msg = message == null || message.isEmpty() ? codeName : message;
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
    return forCode(name, details);
  }

  /**
   * The named error for a failure of a gRPC call: a status exception becomes its
   * CAST error; a CastError passes unchanged; anything else becomes CastError.
   */
  public static CastError fromThrowable(Throwable t) {
    if (t instanceof CastError) {
      return (CastError) t;
    }
    if (t instanceof StatusRuntimeException) {
      return fromStatus(((StatusRuntimeException) t).getStatus());
    }
    if (t instanceof StatusException) {
      return fromStatus(((StatusException) t).getStatus());
    }
    return fromStatus(Status.fromThrowable(t));
  }
}
