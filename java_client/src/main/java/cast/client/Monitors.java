package cast.client;

import java.time.Duration;
import java.util.concurrent.TimeUnit;
import java.util.function.BooleanSupplier;

/** Timed waits on an object's monitor, as the client's drains make them. */
final class Monitors {
  private Monitors() {}

  /**
   * Wait on {@code monitor} (whose lock the caller holds) until {@code done} holds, at most
   * {@code timeout}; false when the time ran out first. An interrupt ends the wait (false) and
   * stays set on the thread, so that whoever owns the thread sees it.
   */
  static boolean waitUntil(Object monitor, BooleanSupplier done, Duration timeout) {
    long deadline = System.nanoTime() + timeout.toNanos();
    try {
      while (!done.getAsBoolean()) {
        long left = deadline - System.nanoTime();
        if (left <= 0) {
          return false;
        }
        TimeUnit.NANOSECONDS.timedWait(monitor, left);
      }
      return true;
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
      return false;
    }
  }
}
