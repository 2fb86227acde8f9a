package cast.client;

import java.math.BigDecimal;
import java.time.Duration;
import java.util.function.Supplier;
import java.util.logging.Logger;

/**
 * A launched component's first contact with its server (docs/client-protocol.md, "Start-up",
 * step 2). Whoever launched the component started the system first, so a server that does not
 * answer at once is busy or still starting: the first call is asked again with backoff for the
 * connect window ({@link #CONNECT_WINDOW}, 20 s) before the runner gives up. The twin of {@code
 * LaunchContract.connect} in python/cast/client/runner.py and of cpp_client/src/connect_window.h:
 * the same codes, the same words.
 */
final class ConnectWindow {
  private static final Logger LOG = Logger.getLogger("cast.run");

  /** How long a launched component keeps asking a server that does not answer before it gives up. */
  static final Duration CONNECT_WINDOW = Duration.ofSeconds(20);

  /** The time and the waits of the window, so that tests can run it on a clock of their own. */
  interface Clock {
    /** A monotonic time in nanoseconds. */
    long nanos();

    /** Waits {@code millis} milliseconds. */
    void sleep(long millis) throws InterruptedException;
  }

  /** The machine's clock. */
  static final Clock SYSTEM =
      new Clock() {
        @Override
        public long nanos() {
          return System.nanoTime();
        }

        @Override
        public void sleep(long millis) throws InterruptedException {
          Thread.sleep(millis);
        }
      };

  private final Duration window;
  private final Clock clock;

  /** The runner's: {@link #CONNECT_WINDOW} on the machine's clock. */
  ConnectWindow() {
    this(CONNECT_WINDOW, SYSTEM);
  }

  /**
   * The runner's, for the launch environment: {@code CAST_CONNECT_WINDOW_S} seconds when set (the
   * same rule and words as Python's {@code connect_window_from}), else {@link #CONNECT_WINDOW}.
   */
  static ConnectWindow fromEnv(java.util.Map<String, String> env) {
    String text = env.getOrDefault("CAST_CONNECT_WINDOW_S", "");
    if (text.isEmpty()) {
      return new ConnectWindow();
    }
    double seconds;
    try {
      seconds = Double.parseDouble(text);
    } catch (NumberFormatException e) {
      seconds = -1;
    }
    if (!(seconds >= 0) || Double.isInfinite(seconds)) {
      throw new InvalidArgumentError(
          "CAST_CONNECT_WINDOW_S '"
              + text
              + "': give the seconds a launched component keeps asking a server that does not answer,"
              + " 0 or more (default 20)");
    }
    return new ConnectWindow(Duration.ofMillis((long) (seconds * 1000)), SYSTEM);
  }

  ConnectWindow(Duration window, Clock clock) {
    this.window = window;
    this.clock = clock;
  }

  /**
   * Whether a failed first contact is asked again: the server is down, still starting
   * (UNAVAILABLE) or too busy to answer in time (DEADLINE_EXCEEDED). Any other failure (a refused
   * token, a bad TLS file) is the launch environment's fault, and asking again would not mend it.
   */
  static boolean retried(CastError e) {
    return e.code().equals("UNAVAILABLE") || e.code().equals("DEADLINE_EXCEEDED");
  }

  /** What the runner says when nothing answered within {@code window}: where, how long, what to check. */
  static String gaveUp(String endpoint, Duration window, boolean tls, CastError last) {
    // 20 s as "20", 1.5 s as "1.5": as Python's {:g}.
    String seconds = BigDecimal.valueOf(window.toMillis(), 3).stripTrailingZeros().toPlainString();
    return "no CAST system answered at "
        + endpoint
        + " within "
        + seconds
        + " s (CAST_ENDPOINT, spoken to "
        + (tls ? "with TLS" : "in plaintext")
        + "): check that the system is running and that CAST_ENDPOINT and CAST_TLS_* are its address and TLS"
        + " settings (last error: "
        + last.getMessage()
        + ")";
  }

  /**
   * The result of {@code attempt} (the first call to the server at {@code endpoint}). A failure
   * {@link #retried} accepts is logged and asked again after a backoff until the window has passed
   * since the first try, then UnavailableError with {@link #gaveUp}; anything else is thrown at
   * once. An interrupt while waiting ends the asking with the last error.
   */
  <T> T connect(String endpoint, boolean tls, Supplier<T> attempt) {
    long deadline = clock.nanos() + window.toNanos();
    Backoff backoff = new Backoff();
    while (true) {
      try {
        return attempt.get();
      } catch (CastError e) {
        if (!retried(e)) {
          throw e;
        }
        if (clock.nanos() - deadline >= 0) {
          throw new UnavailableError(gaveUp(endpoint, window, tls, e));
        }
        LOG.info("the server at " + endpoint + " is not answering yet (" + e.getMessage() + "); asking again");
        try {
          clock.sleep(backoff.nextMillis());
        } catch (InterruptedException interrupted) {
          Thread.currentThread().interrupt();
          throw e;
        }
      }
    }
  }
}
