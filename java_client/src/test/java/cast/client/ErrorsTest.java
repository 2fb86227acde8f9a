package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import io.grpc.Metadata;
import io.grpc.Status;
import java.io.IOException;
import java.io.UncheckedIOException;
import java.nio.file.Files;
import java.nio.file.Path;
import java.util.LinkedHashMap;
import java.util.Map;
import java.util.Set;
import java.util.regex.Matcher;
import java.util.regex.Pattern;
import org.junit.jupiter.api.Test;

class ErrorsTest {
  /**
   * docs/client-protocol.md, "Errors": the table every client library follows, read from the
   * page itself so that the page and this library cannot drift apart. Rows "| CODE | Class |".
   */
  static final Map<Status.Code, Class<? extends CastError>> TABLE = new LinkedHashMap<>();

  /** The same table's rows "| CODE, trailer `cast-error: Class` | Class (a Base) |": the precise errors. */
  static final Map<Class<? extends CastError>, Status.Code> PRECISE = new LinkedHashMap<>();

  static {
    Pattern plain = Pattern.compile("\\| ([A-Z_]+) \\| (\\w+) \\|");
    Pattern precise = Pattern.compile("\\| ([A-Z_]+), trailer `cast-error: (\\w+)` \\| \\2 \\(a \\w+\\) \\|");
    for (String row : errorsSection().split("\n")) {
      Matcher m = plain.matcher(row);
      if (m.matches()) {
        TABLE.put(Status.Code.valueOf(m.group(1)), errorClass(m.group(2)));
      } else if ((m = precise.matcher(row)).matches()) {
        PRECISE.put(errorClass(m.group(2)), Status.Code.valueOf(m.group(1)));
      }
    }
  }

  /** The "Errors" section of docs/client-protocol.md (the tests run in java_client/). */
  static String errorsSection() {
    try {
      String page =
          Files.readString(Path.of(System.getProperty("basedir", "."), "..", "docs", "client-protocol.md"));
      int start = page.indexOf("\n## Errors\n");
      return page.substring(start, page.indexOf("\n## ", start + 1));
    } catch (IOException e) {
      throw new UncheckedIOException(e);
    }
  }

  static Class<? extends CastError> errorClass(String name) {
    try {
      return Class.forName("cast.client." + name).asSubclass(CastError.class);
    } catch (ClassNotFoundException e) {
      throw new AssertionError("docs/client-protocol.md names " + name + ", which cast.client lacks", e);
    }
  }

  @Test
  void theTableIsReadFromThePage() {
    assertEquals(12, TABLE.size(), TABLE.toString());
    assertEquals(LockedError.class, TABLE.get(Status.Code.FAILED_PRECONDITION));
    assertEquals(Set.of(TaskStateError.class, NoSessionError.class, SchemaConflictError.class), PRECISE.keySet());
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
    for (var precise : PRECISE.keySet()) {
      assertEquals(Status.Code.FAILED_PRECONDITION, PRECISE.get(precise));
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
