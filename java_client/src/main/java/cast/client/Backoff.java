package cast.client;

import java.util.concurrent.ThreadLocalRandom;

/** Exponential backoff with jitter for reconnecting: 0.1 s doubling to 3 s (as the Python client). */
final class Backoff {
  private final long initialMillis;
  private final long maxMillis;
  private long next; // guarded by this

  Backoff() {
    this(100, 3_000);
  }

  Backoff(long initialMillis, long maxMillis) {
    this.initialMillis = initialMillis;
    this.maxMillis = maxMillis;
    this.next = initialMillis;
  }

  /** Back to the initial delay (after a successful connection). */
  synchronized void reset() {
    next = initialMillis;
  }

  /** The delay before the next attempt, in milliseconds (grows each time). */
  synchronized long nextMillis() {
    long delay = (long) (next * ThreadLocalRandom.current().nextDouble(0.8, 1.2));
    next = Math.min(maxMillis, next * 2);
    return delay;
  }
}
