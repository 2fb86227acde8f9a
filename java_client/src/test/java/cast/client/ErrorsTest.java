package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import io.grpc.Metadata;
import io.grpc.Status;
import java.util.LinkedHashMap;
import java.util.List;
import java.util.Map;
import org.junit.jupiter.api.Test;

class ErrorsTest {
  /** docs/client-protocol.md, "Errors": the same table in every client library. */
  static final Map<Status.Code, Class<? extends CastError>> TABLE = new LinkedHashMap<>();

  static {
    TABLE.put(Status.Code.ALREADY_EXISTS, AlreadyExistsError.class);
    TABLE.put(Status.Code.NOT_FOUND, NotFoundError.class);
    TABLE.put(Status.Code.ABORTED, ConsistencyError.class);
    TABLE.put(Status.Code.PERMISSION_DENIED, PermissionDeniedError.class);
    TABLE.put(Status.Code.FAILED_PRECONDITION, LockedError.class);
    TABLE.put(Status.Code.INVALID_ARGUMENT, InvalidArgumentError.class);
    TABLE.put(Status.Code.UNAUTHENTICATED, UnauthenticatedError.class);
    TABLE.put(Status.Code.DEADLINE_EXCEEDED, DeadlineExceededError.class);
    TABLE.put(Status.Code.OUT_OF_RANGE, HistoryExpiredError.class);
    TABLE.put(Status.Code.RESOURCE_EXHAUSTED, ResourceExhaustedError.class);
    TABLE.put(Status.Code.UNAVAILABLE, UnavailableError.class);
    TABLE.put(Status.Code.INTERNAL, InternalError.class);
  }

  @Test
  void everyStatusMapsToItsNamedErrorWithTheServersMessage() {
    for (var row : TABLE.entrySet()) {
      String msg = "details of " + row.getKey();
      CastError err = Errors.fromStatus(Status.fromCode(row.getKey()).withDescription(msg));
      assertEquals(row.getValue(), err.getClass(), row.getKey().name());
      assertEquals(row.getKey().name(), err.code());
      if (row.getKey() == Status.Code.UNAVAILABLE) {
        assertTrue(err.getMessage().startsWith("server unavailable (" + msg + "): a write made by this call may"));
      } else {
        assertEquals(msg, err.getMessage(), "the message is the server's status details, unchanged");
      }
      assertTrue(err instanceof RuntimeException);
    }
  }

  @Test
  void codeNamesMapLikeStatuses() {
    for (var row : TABLE.entrySet()) {
      CastError err = Errors.forCode(row.getKey().name(), "m");
      assertEquals(row.getValue(), err.getClass());
      assertEquals("m", err.getMessage());
    }
  }

  @Test
  void anyOtherCodeIsTheBaseClassWithItsCode() {
    CastError err = Errors.fromStatus(Status.CANCELLED.withDescription("gone"));
    assertEquals(CastError.class, err.getClass());
    assertEquals("CANCELLED", err.code());
    assertEquals("gone", err.getMessage());
    assertEquals("UNKNOWN", new CastError("x").code());
  }

  @Test
  void anEmptyDescriptionStillSaysSomething() {
    assertEquals("NOT_FOUND", Errors.fromStatus(Status.NOT_FOUND).getMessage());
  }

  @Test
  void throwablesFromCallsAreMapped() {
    assertEquals(
        LockedError.class,
        Errors.fromThrowable(Status.FAILED_PRECONDITION.withDescription("x").asRuntimeException()).getClass());
    assertEquals(
        ConsistencyError.class, Errors.fromThrowable(Status.ABORTED.withDescription("v").asException()).getClass());
    NotFoundError same = new NotFoundError("same");
    assertSame(same, Errors.fromThrowable(same));
  }

  @Test
  void everyNamedErrorIsACastError() {
    for (var cls : TABLE.values()) {
      assertTrue(CastError.class.isAssignableFrom(cls), cls.getName());
      assertEquals("cast.client", cls.getPackageName());
    }
  }

  /** Trailing metadata as the server sends it next to a status: {@code cast-error: name}. */
  static Metadata trailer(String name) {
    Metadata trailers = new Metadata();
    trailers.put(Metadata.Key.of("cast-error", Metadata.ASCII_STRING_MARSHALLER), name);
    return trailers;
  }

  static final Status WAITING = Status.FAILED_PRECONDITION.withDescription("task t is waiting, not adopted");

  @Test
  void theTrailerNamesAPreciseLockedError() {
    assertEquals("cast-error", Errors.ERROR_TRAILER);
    for (var precise : List.of(TaskStateError.class, NoSessionError.class, SchemaConflictError.class)) {
      CastError err = Errors.fromStatus(WAITING, trailer(precise.getSimpleName()));
      assertEquals(precise, err.getClass());
      assertTrue(err instanceof LockedError, "existing catch (LockedError e) still catches it");
      assertEquals("FAILED_PRECONDITION", err.code());
      assertEquals("task t is waiting, not adopted", err.getMessage());
      assertEquals(precise, Errors.forCode("FAILED_PRECONDITION", "m", precise.getSimpleName()).getClass());
    }
  }

  @Test
  void withoutATrailerItIsALockedError() {
    assertEquals(LockedError.class, Errors.fromStatus(WAITING, null).getClass());
    assertEquals(LockedError.class, Errors.fromStatus(WAITING, new Metadata()).getClass());
    assertNull(Errors.errorName(new Metadata()));
  }

  @Test
  void anUnknownNameInTheTrailerIsIgnored() {
    assertEquals(LockedError.class, Errors.fromStatus(WAITING, trailer("FutureError")).getClass());
    // Only the classes the trailer may name: not the plain ones, nor the base.
    assertEquals(LockedError.class, Errors.fromStatus(WAITING, trailer("NotFoundError")).getClass());
    assertEquals(LockedError.class, Errors.fromStatus(WAITING, trailer("CastError")).getClass());
  }

  @Test
  void aNameOfAnotherCodeIsIgnored() {
    CastError err = Errors.fromStatus(Status.NOT_FOUND.withDescription("no task t"), trailer("TaskStateError"));
    assertEquals(NotFoundError.class, err.getClass());
    assertEquals("no task t", err.getMessage());
    assertEquals(CastError.class, Errors.forCode("SOMETHING_NEW", "m", "TaskStateError").getClass());
  }

  @Test
  void throwablesCarryTheirTrailers() {
    assertEquals(TaskStateError.class, Errors.fromThrowable(WAITING.asRuntimeException(trailer("TaskStateError"))).getClass());
    assertEquals(NoSessionError.class, Errors.fromThrowable(WAITING.asException(trailer("NoSessionError"))).getClass());
    assertEquals(LockedError.class, Errors.fromThrowable(WAITING.asRuntimeException()).getClass());
  }
}
