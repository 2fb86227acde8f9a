package cast.testing;

import cast.client.WorkingMemoryChange;
import com.google.protobuf.Message;
import com.google.protobuf.TextFormat;
import java.time.Duration;
import java.util.function.BooleanSupplier;
import java.util.function.Supplier;

/**
 * The kit's functions that need no system: waiting for a condition with a failure that says what
 * was seen, and one-line words for values and changes. {@code import static
 * cast.testing.CastTesting.waitFor;} gives the name the Python and C++ kits use.
 */
public final class CastTesting {
  /** How long the kit waits when a test does not say (as in Python and C++): a guard against a hang. */
  public static final Duration DEFAULT_TIMEOUT = Duration.ofSeconds(10);

  private static final int MAX_VALUE_CHARS = 300;

  private CastTesting() {}

  /** {@link #waitFor(BooleanSupplier, Duration, String, Supplier)} for 10 s. */
  public static void waitFor(BooleanSupplier condition, String what) {
    waitFor(condition, DEFAULT_TIMEOUT, what, null);
  }

  /** {@link #waitFor(BooleanSupplier, Duration, String, Supplier)} without a description of what was seen. */
  public static void waitFor(BooleanSupplier condition, Duration timeout, String what) {
    waitFor(condition, timeout, what, null);
  }

  /**
   * Asks {@code condition} every 10 ms until it returns true, and once more when the time is up;
   * then throws AssertionError naming {@code what} and the timeout, with {@code seen.get()} if
   * given. A condition may also throw AssertionError, meaning "not yet": its last message is what
   * a timeout reports.
   */
  public static void waitFor(BooleanSupplier condition, Duration timeout, String what, Supplier<String> seen) {
    long deadline = System.nanoTime() + timeout.toNanos();
    while (true) {
      AssertionError failure = null;
      try {
        if (condition.getAsBoolean()) {
          return;
        }
      } catch (AssertionError e) {
        failure = e;
      }
      if (System.nanoTime() - deadline >= 0) {
        String message = "timed out after " + seconds(timeout) + " s waiting for " + what;
        if (failure != null) {
          throw new AssertionError(message + ": " + failure.getMessage(), failure);
        }
        throw new AssertionError(seen == null ? message : message + "; seen: " + seen.get());
      }
      try {
        Thread.sleep(10);
      } catch (InterruptedException e) {
        Thread.currentThread().interrupt();
        throw new AssertionError("interrupted while waiting for " + what, e);
      }
    }
  }

  /** A value as its type and its fields on one line: {@code google.protobuf.Int64Value {value: 3}}. */
  public static String describeValue(Message value) {
    String text = value.getDescriptorForType().getFullName() + " {" + TextFormat.shortDebugString(value) + "}";
    return text.length() <= MAX_VALUE_CHARS
        ? text
        : text.substring(0, MAX_VALUE_CHARS) + "... (" + text.length() + " characters)";
  }

  /** One line for a change: {@code ADD vision/count by counter (revision 3): google.protobuf.Int64Value}. */
  public static String describeChange(WorkingMemoryChange change) {
    return change.operation() + " " + change.subarchitecture() + "/" + change.id() + " by "
        + change.sourceComponent() + " (revision " + change.revision() + "): " + change.type();
  }

  /** Seconds as the other kits write them: 10, 0.2. */
  static String seconds(Duration duration) {
    double s = duration.toMillis() / 1000.0;
    return s == Math.rint(s) ? Long.toString((long) s) : Double.toString(s);
  }
}
