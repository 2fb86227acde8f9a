package cast.client;

import java.time.Duration;
import java.util.concurrent.LinkedBlockingQueue;
import java.util.concurrent.TimeUnit;
import java.util.logging.Level;
import java.util.logging.Logger;

/**
 * One thread per component that runs its callbacks and hooks one at a time, in
 * the order they were queued. A failing callback is logged, not fatal: one bad
 * callback must not stop the others.
 *
 * <p>The queue is bounded by {@code capacity}: a blocking submit (from a stream's
 * reader) waits for room, so a component whose callbacks are slow stops reading
 * its Watch stream and lags on the server, which keeps a bounded history and
 * says so (HistoryExpiredError) past it, instead of the client buffering without
 * bound. The same policy as the Python client (docs/decisions.md).
 */
final class Dispatcher {
  private static final Logger LOG = Logger.getLogger("cast.component");
  private static final Runnable END = () -> {};

  private final LinkedBlockingQueue<Runnable> queue = new LinkedBlockingQueue<>();
  private final Thread thread;
  private final Object idle = new Object();
  private final int capacity;
  private long pending; // guarded by idle

  Dispatcher(String name, int capacity) {
    if (capacity < 1) {
      throw new InvalidArgumentError("the dispatcher's capacity must be at least 1, got " + capacity);
    }
    this.capacity = capacity;
    thread = new Thread(this::loop, "cast-dispatch-" + name);
    thread.setDaemon(true);
    thread.start();
  }

  /** The dispatcher thread. */
  Thread thread() {
    return thread;
  }

  /** Calls queued or running. */
  long pending() {
    synchronized (idle) {
      return pending;
    }
  }

  /** Queue a call without waiting (hooks, errors: never held up by a full queue). */
  void submit(Runnable call) {
    synchronized (idle) {
      pending++;
    }
    queue.add(call);
  }

  /**
   * Queue a call, first waiting while the queue is full (except on the dispatcher
   * thread itself, which would wait for itself).
   */
  void submitBlocking(Runnable call) throws InterruptedException {
    synchronized (idle) {
      while (pending >= capacity && Thread.currentThread() != thread) {
        idle.wait();
      }
      pending++;
    }
    queue.add(call);
  }

  private void loop() {
    while (true) {
      Runnable call;
      try {
        call = queue.take();
      } catch (InterruptedException e) {
        return;
      }
      if (call == END) {
        return;
      }
      try {
        call.run();
      } catch (Throwable t) { // a callback's failure is reported, the dispatcher goes on
        LOG.log(Level.SEVERE, thread.getName() + ": callback failed", t);
      } finally {
        synchronized (idle) {
          pending--;
          if (pending == 0 || pending == capacity - 1) {
            idle.notifyAll(); // drain() waits for 0, submitBlocking() for room
          }
        }
      }
    }
  }

  /** Wait until every call queued so far has run; false on timeout (null: wait forever). */
  boolean drain(Duration timeout) throws InterruptedException {
    long deadline = timeout == null ? Long.MAX_VALUE : System.nanoTime() + timeout.toNanos();
    synchronized (idle) {
      while (pending > 0) {
        if (Thread.currentThread() == thread) {
          return false; // a callback waiting for itself would wait forever
        }
        long left = deadline - System.nanoTime();
        if (left <= 0) {
          return false;
        }
        TimeUnit.NANOSECONDS.timedWait(idle, Math.min(left, TimeUnit.SECONDS.toNanos(3600)));
      }
      return true;
    }
  }

  /** Run what is queued, then end the thread (waits up to {@code timeout} unless called from it). */
  void stop(Duration timeout) {
    queue.add(END);
    if (Thread.currentThread() != thread) {
      try {
        thread.join(timeout.toMillis());
      } catch (InterruptedException e) {
        Thread.currentThread().interrupt();
      }
    }
  }
}
