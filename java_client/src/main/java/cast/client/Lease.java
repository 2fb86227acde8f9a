package cast.client;

import java.lang.ref.Cleaner;
import java.nio.ByteBuffer;
import java.util.concurrent.atomic.AtomicInteger;

/**
 * A value the server lent by shared memory (docs/client-protocol.md, "Reading large values"):
 * its bytes, read-only in a segment mapped once, and how many holders it has. The entry read
 * or the change event that brought it is its first holder; a {@link ValueView} is another, a
 * callback being delivered another. When the last one lets it go the value is given back
 * (RELEASE), and from then on nothing reads the bytes through it ({@link #retain} is false):
 * the server may reuse their place.
 *
 * <p>A lease nobody released (a view never closed) is given back once it is garbage, by a
 * {@link Cleaner}: late, but the server's window for this client is not lost for good.
 */
final class Lease {
  /** The library's cleaner of shared-memory holdings left to the collector: leases, and loans ({@link Loan}). */
  static final Cleaner CLEANER =
      Cleaner.create(
          r -> {
            Thread t = new Thread(r, "cast-shm-leases");
            t.setDaemon(true);
            return t;
          });

  /** What the cleaner needs: never the lease itself, or it would never be garbage. */
  private static final class Holders implements Runnable {
    final AtomicInteger count = new AtomicInteger(1);
    final Runnable giveBack;

    Holders(Runnable giveBack) {
      this.giveBack = giveBack;
    }

    @Override
    public void run() { // the lease is garbage, or its last holder let go (then count is 0 already)
      if (count.getAndSet(0) > 0) {
        giveBack.run();
      }
    }
  }

  private final ByteBuffer bytes;
  private final Holders holders;
  private final Cleaner.Cleanable cleanable;

  /** A lease of {@code bytes} (the whole value) held once; {@code giveBack} runs when the last holder goes. */
  Lease(ByteBuffer bytes, Runnable giveBack) {
    this.bytes = bytes.asReadOnlyBuffer();
    this.holders = new Holders(giveBack);
    this.cleanable = CLEANER.register(this, holders);
  }

  /** The value's bytes, read-only, from position 0 (a new buffer each time: its position is the caller's). */
  ByteBuffer bytes() {
    return bytes.duplicate();
  }

  /** The value's size in bytes. */
  int size() {
    return bytes.capacity();
  }

  /** One more holder; false when the value was given back already (its bytes must not be read). */
  boolean retain() {
    while (true) {
      int n = holders.count.get();
      if (n <= 0) {
        return false;
      }
      if (holders.count.compareAndSet(n, n + 1)) {
        return true;
      }
    }
  }

  /** A holder lets go; the last one gives the value back. Extra calls do nothing. */
  void release() {
    while (true) {
      int n = holders.count.get();
      if (n <= 0) {
        return;
      }
      if (holders.count.compareAndSet(n, n - 1)) {
        if (n == 1) {
          holders.giveBack.run();
          cleanable.clean(); // nothing left to do for the cleaner (count is 0)
        }
        return;
      }
    }
  }

  /** Whether some holder still holds the value. */
  boolean isHeld() {
    return holders.count.get() > 0;
  }
}
