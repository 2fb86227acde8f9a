package cast.client;

import java.time.Duration;

/**
 * What is left of one call's timeout. Opening the shared-memory session on a call's way (the
 * first large write, or a read) spends from it, so that a hung server holds the call for its
 * timeout, not for the opening's own bounds and then the timeout again (docs/client-protocol.md,
 * "Deadlines"). Part of the {@code grpc_transport} role, as {@code _Budget} is in
 * python/cast/client/grpc_transport.py.
 */
final class Budget {
  private final long end; // System.nanoTime()

  Budget(Duration timeout) {
    this.end = System.nanoTime() + timeout.toNanos();
  }

  /** The time left; DeadlineExceededError once there is none (nothing was sent). */
  Duration left() {
    long left = end - System.nanoTime();
    if (left <= 0) {
      throw new DeadlineExceededError(
          "the call's deadline passed while opening shared memory with the server: nothing was sent; the server may "
              + "be hung or overloaded, retry later");
    }
    return Duration.ofNanos(left);
  }
}
