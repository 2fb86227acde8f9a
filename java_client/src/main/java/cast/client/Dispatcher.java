package cast.client;

import java.time.Duration;
import java.util.ArrayList;
import java.util.Iterator;
import java.util.LinkedHashMap;
import java.util.List;
import java.util.Map;
import java.util.concurrent.ConcurrentHashMap;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicInteger;
import java.util.function.BooleanSupplier;
import java.util.logging.Level;
import java.util.logging.Logger;

/**
 * One thread per component that runs its callbacks and hooks one at a time, and the
 * component's watch callbacks by watch id: a change event goes to the callback of every
 * watch it matched. A failing callback is logged, not fatal: one bad callback must not stop
 * the others.
 *
 * <p>Pending calls wait in one FIFO per {@link Priority}: the dispatcher takes the oldest call
 * of the highest priority that has one, so one watch's changes stay in order and hooks (at
 * MEDIUM) keep theirs. A watch with {@link Delivery#LATEST} keeps at most one undelivered
 * change per entry: a newer change of the entry replaces it (counting it and what it had
 * skipped into {@link WorkingMemoryChange#skipped()}) and goes to the back, so its watch's
 * changes stay in revision order.
 *
 * <p>The queue is bounded by {@code capacity}: a blocking submit (from a stream's
 * reader) waits for room, so a component whose callbacks are slow stops reading
 * its Watch stream and lags on the server, which keeps a bounded history and
 * says so (HistoryExpiredError) past it, instead of the client buffering without
 * bound. The same policy as the Python client (docs/decisions.md).
 */
final class Dispatcher {
  private static final Logger LOG = Logger.getLogger("cast.component");

  private final Thread thread;
  private final Object lock = new Object();
  private final int capacity;
  private final Logger log; // the component's: a failing callback is its failure
  private final Map<Integer, Registration> callbacks = new ConcurrentHashMap<>();
  private final AtomicInteger watchIds = new AtomicInteger();
  // One FIFO per priority, HIGH first. A call's key is itself, or for a LATEST watch's change
  // (watch, entry), so that a newer change of the entry finds the one it replaces.
  private final List<LinkedHashMap<Object, Runnable>> levels = new ArrayList<>(); // guarded by lock
  private long pending; // queued or running; guarded by lock
  private boolean stopped; // guarded by lock

  private record Registration(ChangeCallback callback, WatchHandle handle, WatchOptions options) {}

  /** Where a LATEST watch's undelivered change of one entry waits. */
  private record LatestKey(int watchId, WorkingMemoryAddress address) {}

  /** A LATEST watch's undelivered change; a newer one of the same entry takes its place. */
  private final class LatestCall implements Runnable {
    final int watchId;
    final Transport.Change change;

    LatestCall(int watchId, Transport.Change change) {
      this.watchId = watchId;
      this.change = change;
    }

    @Override
    public void run() {
      WorkingMemoryChange delivered = new WorkingMemoryChange(change);
      try {
        Dispatcher.this.run(watchId, delivered);
      } finally {
        delivered.callbackReturned();
        release(change);
      }
    }
  }

  Dispatcher(String name, int capacity, Logger log) {
    if (capacity < 1) {
      throw new InvalidArgumentError("the dispatcher's capacity must be at least 1, got " + capacity);
    }
    this.capacity = capacity;
    this.log = log;
    for (int i = 0; i < Priority.values().length; i++) {
      levels.add(new LinkedHashMap<>());
    }
    thread = new Thread(this::loop, "cast-dispatch-" + name);
    thread.setDaemon(true);
    thread.start();
  }

  /** The dispatcher thread. */
  Thread thread() {
    return thread;
  }

  /** Whether {@link #stop} was called. */
  boolean isStopped() {
    synchronized (lock) {
      return stopped;
    }
  }

  /** Calls queued or running. */
  long pending() {
    synchronized (lock) {
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

  /** Queue a call at MEDIUM priority without waiting (hooks, errors: never held up by a full queue). */
  void submit(Runnable call) {
    submit(Priority.MEDIUM, call);
  }

  /** Queue a call at {@code priority} without waiting. */
  void submit(Priority priority, Runnable call) {
    synchronized (lock) {
      add(priority, call, call);
    }
  }

  /**
   * Queue a call at MEDIUM priority, first waiting while the queue is full (except on the
   * dispatcher thread itself, which would wait for itself).
   */
  void submitBlocking(Runnable call) throws InterruptedException {
    submitBlocking(Priority.MEDIUM, call);
  }

  /** Queue a call at {@code priority}, first waiting while the queue is full. */
  void submitBlocking(Priority priority, Runnable call) throws InterruptedException {
    synchronized (lock) {
      awaitRoom();
      add(priority, call, call);
    }
  }

  /** Wait while the queue is full (holding lock); never on the dispatcher thread. */
  private void awaitRoom() throws InterruptedException {
    awaitRoom(NEVER);
  }

  private static final BooleanSupplier NEVER = () -> false;
  /** How often a wait for room looks at its {@code overflow} condition again. */
  private static final long OVERFLOW_CHECK_MS = 5;

  /**
   * Wait while the queue is full (holding lock); never on the dispatcher thread, nor while
   * {@code overflow} holds (then the call goes over the capacity rather than wait).
   */
  private void awaitRoom(BooleanSupplier overflow) throws InterruptedException {
    while (pending >= capacity && !stopped && Thread.currentThread() != thread) {
      if (overflow == NEVER) {
        lock.wait();
      } else if (overflow.getAsBoolean()) {
        return;
      } else {
        lock.wait(OVERFLOW_CHECK_MS);
      }
    }
  }

  /** Queue {@code call} under {@code key} (holding lock); false (dropped) once the dispatcher stopped. */
  private boolean add(Priority priority, Object key, Runnable call) {
    if (stopped) {
      return false; // stop() runs what was queued before it, nothing after
    }
    levels.get(priority.ordinal()).put(key, call);
    pending++;
    lock.notifyAll();
    return true;
  }

  /** The oldest call of the highest priority that has one, taken off its queue; null if none (holding lock). */
  private Runnable next() {
    for (LinkedHashMap<Object, Runnable> level : levels) {
      if (!level.isEmpty()) {
        Iterator<Runnable> it = level.values().iterator();
        Runnable call = it.next();
        it.remove();
        return call;
      }
    }
    return null;
  }

  private void loop() {
    // One call per runNext: the JIT compiles a method by its calls, but this loop, entered once,
    // only by its back-edges, so the work of each call kept in it ran in the bytecode interpreter
    // for tens of thousands of calls (docs/performance-m8.md, "The Java watcher's loops in the
    // interpreter").
    while (runNext()) {
      // the next call, until the dispatcher stops
    }
  }

  /** Wait for the next call and run it; false once the dispatcher stopped (or was interrupted). */
  private boolean runNext() {
    Runnable call;
    synchronized (lock) {
      while ((call = next()) == null) {
        if (stopped) {
          return false;
        }
        try {
          lock.wait();
        } catch (InterruptedException e) {
          return false;
        }
      }
    }
    try {
      call.run();
    } catch (Throwable t) { // a callback's failure is reported, the dispatcher goes on
      LOG.log(Level.SEVERE, thread.getName() + ": callback failed", t);
    } finally {
      synchronized (lock) {
        pending--;
        lock.notifyAll(); // drain() waits for 0, a blocking submit for room
      }
    }
    return true;
  }

  // ------------------------------------------------------- watch callbacks

  /**
   * Register {@code callback} under a new watch id, then create the watch through
   * {@code transport} (filters with their SA filled in); the handle cancels both.
   */
  WatchHandle watch(Transport transport, List<ChangeFilter> filters, ChangeCallback callback, WatchOptions options) {
    int watchId = watchIds.incrementAndGet();
    WatchHandle handle = new WatchHandle(this, transport, watchId);
    // Registered before the create is sent: events may arrive before the confirmation.
    callbacks.put(watchId, new Registration(callback, handle, options));
    try {
      transport.watch(watchId, filters, Map.of(), options.delivery());
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
   *
   * <p>A value lent by shared memory is held for each callback it is queued for, until that
   * callback returned (or the call was dropped); the change's own hold is let go here. A view
   * the callback takes ({@link WorkingMemoryChange#view()}) holds it longer; otherwise the
   * change keeps a copy of the value once its callback returned
   * ({@link WorkingMemoryChange#callbackReturned()}).
   */
  void deliver(Transport.Change change) {
    deliver(change, NEVER);
  }

  /**
   * As {@link #deliver(Transport.Change)}, but while {@code overflow} holds the change is queued
   * over the capacity instead of waiting for room (a shared-memory session's reader, which must
   * go on reading while a thread waits for a segment, or a write for its reply, that may be behind
   * this change's frame).
   */
  void deliver(Transport.Change change, BooleanSupplier overflow) {
    try {
      WorkingMemoryChange c = null;
      for (int watchId : change.watchIds()) {
        Registration r = callbacks.get(watchId);
        if (r == null) {
          continue;
        }
        if (r.options().delivery() == Delivery.LATEST) {
          deliverLatest(r.options().priority(), watchId, change, overflow);
          continue;
        }
        if (c == null) {
          c = new WorkingMemoryChange(change);
        }
        WorkingMemoryChange delivered = c;
        retain(change);
        Runnable call =
            () -> {
              try {
                run(watchId, delivered);
              } finally {
                delivered.callbackReturned();
                release(change);
              }
            };
        boolean queued = false;
        try {
          synchronized (lock) {
            awaitRoom(overflow);
            queued = add(r.options().priority(), call, call);
          }
        } finally {
          if (!queued) {
            release(change);
          }
        }
      }
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
    } finally {
      release(change);
    }
  }

  /** One more hold of the change's lent value, if it has one. */
  private static void retain(Transport.Change change) {
    if (change.entry() != null) {
      change.entry().retain();
    }
  }

  /** Let go of one hold of the change's lent value, if it has one. */
  private static void release(Transport.Change change) {
    if (change.entry() != null) {
      change.entry().release();
    }
  }

  /** Queue a LATEST watch's change, in place of an undelivered one of the same entry if there is one. */
  private void deliverLatest(Priority priority, int watchId, Transport.Change change, BooleanSupplier overflow)
      throws InterruptedException {
    LatestKey key = new LatestKey(watchId, change.address());
    LinkedHashMap<Object, Runnable> level = levels.get(priority.ordinal());
    retain(change); // the queued call's hold: let go when it ran, was replaced or dropped
    boolean queued = false;
    try {
      synchronized (lock) {
        queued = replaced(level, key, watchId, change);
        if (!queued) {
          awaitRoom(overflow);
          queued = replaced(level, key, watchId, change) || add(priority, key, new LatestCall(watchId, change));
        }
      }
    } finally {
      if (!queued) {
        release(change);
      }
    }
  }

  /**
   * Replace the undelivered change under {@code key} by {@code change} (now at the back of
   * its queue, the pending count unchanged); false if there is none (holding lock).
   */
  private boolean replaced(LinkedHashMap<Object, Runnable> level, LatestKey key, int watchId, Transport.Change change) {
    Runnable queued = level.remove(key);
    if (queued == null) {
      return false;
    }
    Transport.Change older = ((LatestCall) queued).change;
    level.put(key, new LatestCall(watchId, change.superseding(older)));
    release(older); // never delivered: its value goes back at once
    return true;
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
    synchronized (lock) {
      while (pending > 0) {
        if (Thread.currentThread() == thread) {
          return false; // a callback waiting for itself would wait forever
        }
        long left = deadline - System.nanoTime();
        if (left <= 0) {
          return false;
        }
        TimeUnit.NANOSECONDS.timedWait(lock, Math.min(left, TimeUnit.SECONDS.toNanos(3600)));
      }
      return true;
    }
  }

  /**
   * Run what is queued, then end the thread (waits up to {@code timeout} unless called from
   * it); what is queued after this is dropped.
   */
  void stop(Duration timeout) {
    synchronized (lock) {
      stopped = true;
      lock.notifyAll();
    }
    if (Thread.currentThread() != thread) {
      try {
        thread.join(timeout.toMillis());
      } catch (InterruptedException e) {
        Thread.currentThread().interrupt();
      }
    }
  }
}
