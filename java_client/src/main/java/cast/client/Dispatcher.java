package cast.client;

import java.time.Duration;
import java.util.List;
import java.util.Map;
import java.util.concurrent.ConcurrentHashMap;
import java.util.concurrent.LinkedBlockingQueue;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicInteger;
import java.util.logging.Level;
import java.util.logging.Logger;

/**
 * One thread per component that runs its callbacks and hooks one at a time, in
 * the order they were queued, and the component's watch callbacks by watch id: a
 * change event goes to the callback of every watch it matched. A failing callback
 * is logged, not fatal: one bad callback must not stop the others.
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
  private final Logger log; // the component's: a failing callback is its failure
  private final Map<Integer, Registration> callbacks = new ConcurrentHashMap<>();
  private final AtomicInteger watchIds = new AtomicInteger();
  private long pending; // guarded by idle

  private record Registration(ChangeCallback callback, WatchHandle handle) {}

  Dispatcher(String name, int capacity, Logger log) {
    if (capacity < 1) {
      throw new InvalidArgumentError("the dispatcher's capacity must be at least 1, got " + capacity);
    }
    this.capacity = capacity;
    this.log = log;
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

  /** A hook invocation that may throw. */
  @FunctionalInterface
  interface Hook {
    void run() throws Exception;
  }

  /** Queue a hook (never held up by a full queue); its failure is logged as the component's. */
  void submitHook(Hook hook) {
    submit(
        () -> {
          try {
            hook.run();
          } catch (Exception e) {
            log.log(Level.SEVERE, "hook failed", e);
          }
        });
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

  // ------------------------------------------------------- watch callbacks

  /**
   * Register {@code callback} under a new watch id, then create the watch through
   * {@code transport} (filters with their SA filled in); the handle cancels both.
   */
  WatchHandle watch(Transport transport, List<ChangeFilter> filters, ChangeCallback callback) {
    int watchId = watchIds.incrementAndGet();
    WatchHandle handle = new WatchHandle(this, transport, watchId);
    // Registered before the create is sent: events may arrive before the confirmation.
    callbacks.put(watchId, new Registration(callback, handle));
    try {
      transport.watch(watchId, filters, Map.of());
    } catch (RuntimeException e) {
      callbacks.remove(watchId);
      throw e;
    }
    return handle;
  }

  /** Stop delivering to watch {@code watchId}; false if it was not registered. */
  boolean unregister(int watchId) {
    return callbacks.remove(watchId) != null;
  }

  /** Whether watch {@code watchId} is registered. */
  boolean isRegistered(int watchId) {
    return callbacks.containsKey(watchId);
  }

  /**
   * Queue {@code change} for the callback of every registered watch it matched (called
   * by a stream's reader: waits while the queue is full, so the server holds the rest).
   */
  void deliver(Transport.Change change) {
    WorkingMemoryChange c = null;
    for (int watchId : change.watchIds()) {
      if (!callbacks.containsKey(watchId)) {
        continue;
      }
      if (c == null) {
        c = new WorkingMemoryChange(change);
      }
      WorkingMemoryChange delivered = c;
      try {
        submitBlocking(() -> run(watchId, delivered));
      } catch (InterruptedException e) {
        Thread.currentThread().interrupt();
        return;
      }
    }
  }

  private void run(int watchId, WorkingMemoryChange change) {
    Registration r = callbacks.get(watchId);
    if (r == null) {
      return; // cancelled while queued: dropped, as promised by WatchHandle.cancel
    }
    try {
      r.callback().onChange(change);
    } catch (Exception e) {
      log.log(Level.SEVERE, "change callback failed on " + change, e);
    }
  }

  /**
   * Change delivery stopped with {@code error}: for watch {@code watchId}, which is
   * dropped, or for every watch ({@code watchId} -1). Their handles report the error.
   */
  void stopped(CastError error, int watchId) {
    if (watchId >= 0) {
      Registration r = callbacks.remove(watchId);
      if (r != null) {
        r.handle().setError(error);
      }
    } else {
      for (Registration r : callbacks.values()) {
        r.handle().setError(error);
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
