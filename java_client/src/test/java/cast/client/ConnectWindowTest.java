package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.function.Supplier;
import org.junit.jupiter.api.Test;

/**
 * The first contact of a launched component (ConnectWindow): which failures are asked again, when
 * the window ends, and what the runner then says. Runs on a clock of its own: the waits only move
 * that clock forward.
 */
class ConnectWindowTest {
  /** A clock that stands still except when the code under test waits. */
  static final class FakeClock implements ConnectWindow.Clock {
    long nanos;
    final List<Long> waits = new ArrayList<>();

    @Override
    public long nanos() {
      return nanos;
    }

    @Override
    public void sleep(long millis) {
      waits.add(millis);
      nanos += Duration.ofMillis(millis).toNanos();
    }
  }

  /** Fails with {@code failures} in order, then answers "connected"; counts its calls. */
  static final class Attempt implements Supplier<String> {
    final List<CastError> failures;
    int calls;

    Attempt(List<CastError> failures) {
      this.failures = failures;
    }

    @Override
    public String get() {
      int i = calls++;
      if (i < failures.size()) {
        throw failures.get(i);
      }
      return "connected";
    }
  }

  static UnavailableError refused() {
    return new UnavailableError("server unavailable (connection refused)");
  }

  @Test
  void theWindowIsTwentySecondsAsInPython() {
    assertEquals(Duration.ofSeconds(20), ConnectWindow.CONNECT_WINDOW);
  }

  @Test
  void onlyAServerThatIsDownStartingOrBusyIsAskedAgain() {
    assertTrue(ConnectWindow.retried(refused()));
    assertTrue(ConnectWindow.retried(new DeadlineExceededError("Deadline Exceeded")));
    assertFalse(ConnectWindow.retried(new UnauthenticatedError("token signature does not match")));
    assertFalse(ConnectWindow.retried(new InvalidArgumentError("the launch environment and the token disagree")));
    assertFalse(ConnectWindow.retried(new PermissionDeniedError("no")));
    assertFalse(ConnectWindow.retried(new InternalError("bug")));
  }

  @Test
  void aServerThatAnswersLateIsAskedAgainWithBackoff() {
    FakeClock clock = new FakeClock();
    Attempt attempt = new Attempt(List.of(refused(), new DeadlineExceededError("Deadline Exceeded"), refused()));
    assertEquals("connected", new ConnectWindow(ConnectWindow.CONNECT_WINDOW, clock).connect("h:1", false, attempt));
    assertEquals(4, attempt.calls);
    assertEquals(3, clock.waits.size());
    assertTrue(clock.waits.get(0) < clock.waits.get(2), "the waits grow: " + clock.waits);
  }

  @Test
  void otherErrorsFailAtOnce() {
    FakeClock clock = new FakeClock();
    Attempt attempt = new Attempt(List.of(new UnauthenticatedError("token signature does not match")));
    ConnectWindow window = new ConnectWindow(ConnectWindow.CONNECT_WINDOW, clock);
    assertThrows(UnauthenticatedError.class, () -> window.connect("h:1", false, attempt));
    assertEquals(1, attempt.calls);
    assertTrue(clock.waits.isEmpty());
    // A target gRPC cannot parse is not a server that is late either.
    assertThrows(
        IllegalArgumentException.class,
        () -> window.connect("bad", false, () -> {
          throw new IllegalArgumentException("bad target");
        }));
    assertTrue(clock.waits.isEmpty());
  }

  @Test
  void givesUpWhenTheWindowHasPassedSayingWhereForHowLongAndWhatToCheck() {
    FakeClock clock = new FakeClock();
    List<CastError> forever = new ArrayList<>();
    for (int i = 0; i < 1000; i++) {
      forever.add(refused());
    }
    Attempt attempt = new Attempt(forever);
    ConnectWindow window = new ConnectWindow(ConnectWindow.CONNECT_WINDOW, clock);
    UnavailableError e = assertThrows(UnavailableError.class, () -> window.connect("127.0.0.1:4711", true, attempt));
    assertEquals(
        "no CAST system answered at 127.0.0.1:4711 within 20 s (CAST_ENDPOINT, spoken to with TLS): check that the"
            + " system is running and that CAST_ENDPOINT and CAST_TLS_* are its address and TLS settings (last error:"
            + " server unavailable (connection refused))",
        e.getMessage());
    assertTrue(attempt.calls > 2, "asked again before giving up");
    assertTrue(attempt.calls < 100, "the backoff grows: the window is not spent knocking");
    assertTrue(clock.nanos >= ConnectWindow.CONNECT_WINDOW.toNanos());
  }

  @Test
  void anEmptyWindowGivesUpAfterTheFirstTry() {
    Attempt attempt = new Attempt(List.of(refused()));
    ConnectWindow window = new ConnectWindow(Duration.ZERO, new FakeClock());
    assertThrows(UnavailableError.class, () -> window.connect("h:1", false, attempt));
    assertEquals(1, attempt.calls);
  }

  @Test
  void gaveUpSaysTheWindowAsPythonDoes() {
    String said = ConnectWindow.gaveUp("h:1", Duration.ofMillis(1500), false, refused());
    assertTrue(said.contains("within 1.5 s (CAST_ENDPOINT, spoken to in plaintext)"), said);
  }
}
