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
 *
 * <p>The thread also reads the component's shared-memory session socket while it has nothing to
 * run ({@link #attach}: a socket that carries a watch's events, docs/client-protocol.md "A watch's
 * events on the session's socket"): blocked in the socket's read, it handles what comes itself,
 * so an event's callback runs on the thread the kernel woke for its frame, with no hand-off
 * between threads (docs/performance-m8.md, "The Java dispatcher reads the session's socket,
 * blocked in its read"). A call queued by another thread meanwhile wakes it by a NUDGE, which the
 * server answers on the socket. Before each call it reads what the socket already holds, so a
 * change of a higher priority still goes first; while one call runs longer than {@link
 * SessionSocket#STANDBY_MS}, the socket's reader thread reads in its place.
 */
final class Dispatcher {
  private static final Logger LOG = Logger.getLogger("cast.component");

  /**
   * A socket the dispatcher thread reads while it has nothing to run: a shared-memory session's
   * ({@link SessionSocket}), whose reader thread reads it the rest of the time.
   */
  interface Source {
    /**
     * Read once and handle what was read on this thread; with {@code onlyIfReady}, only if bytes
     * are there already (else nothing), without it blocked until something comes. False at once,
     * reading nothing, when another thread reads it; true once it ended.
     */
    boolean read(boolean onlyIfReady);

    /** Wake the thread blocked in {@link #read}: a NUDGE, which the server answers on the socket. */
    void nudge();

    /** Whether it ended (the dispatcher then forgets it). */
    boolean ended();

    /** {@code d} reads it from now on while it has nothing to run, or no dispatcher does (null). */
    void dispatched(Dispatcher d);

    /** A call began on the dispatcher thread (its standby, asleep while the dispatcher was idle, wakes to watch it). */
    void callBegan();
  }

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
  // The socket the thread reads while idle (attach); written under lock, read without it before a call.
  private volatile Source source;
  private Source inRead; // what the thread is in read(false) of, or about to be; null else; guarded by lock
  private boolean nudged; // a NUDGE was sent for that read; guarded by lock
  private boolean sourceBusy; // another thread read the source when this one tried; guarded by lock
  private long freed; // times a thread let the source go (sourceFree); guarded by lock
  private volatile long callStarted; // System.nanoTime() at the start of the call running now; 0 between calls
  private volatile long lastCallEnded = System.nanoTime(); // when the last call returned (the standby's idle)

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
    if (Thread.currentThread() != thread) {
      wakeFromRead(); // it then runs what was queued
    }
    return true;
  }

  /** The thread, if blocked in a source's read, is woken: one NUDGE per read, its answer ends it (holding lock). */
  private void wakeFromRead() {
    if (inRead != null && !nudged) {
      nudged = true;
      inRead.nudge();
    }
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
    try {
      while (runNext()) {
        // the next call, until the dispatcher stops
      }
    } finally {
      Source s;
      synchronized (lock) {
        s = source;
        source = null;
      }
      if (s != null) {
        s.dispatched(null); // its reader thread reads it again, for as long as it lives
      }
    }
  }

  /**
   * Wait for the next call and run it; false once the dispatcher stopped (or was interrupted).
   * With a source attached and nothing to run, the wait is one read of the source (what it brings
   * is queued on this thread); with a call to run, what the source holds already is read first.
   */
  private boolean runNext() {
    Runnable call;
    Source reading = null;
    long seen = 0;
    synchronized (lock) {
      while ((call = next()) == null) {
        if (stopped) {
          return false;
        }
        Source s = source;
        if (s != null && s.ended()) {
          source = null; // its session ended; a new session's socket is attached by its watch
        } else if (s != null && !sourceBusy) {
          inRead = s;
          nudged = false;
          seen = freed;
          reading = s;
          break;
        }
        try {
          lock.wait();
        } catch (InterruptedException e) {
          return false;
        }
      }
      if (call != null && pending <= capacity && !sourceBusy) {
        reading = source;
        seen = freed;
      }
    }
    if (call == null) {
      readSource(reading, false, seen);
      return true;
    }
    if (reading != null) {
      readSource(reading, true, seen);
    }
    callStarted = System.nanoTime();
    Source s = source;
    if (s != null) {
      s.callBegan();
    }
    try {
      call.run();
    } catch (Throwable t) { // a callback's failure is reported, the dispatcher goes on
      LOG.log(Level.SEVERE, thread.getName() + ": callback failed", t);
    } finally {
      callStarted = 0;
      lastCallEnded = System.nanoTime();
      synchronized (lock) {
        pending--;
        lock.notifyAll(); // drain() waits for 0, a blocking submit for room
      }
    }
    return true;
  }

  /** One read of {@code s} on this thread; if another thread reads it, wait (in runNext) until it lets go. */
  private void readSource(Source s, boolean onlyIfReady, long seen) {
    boolean read = false;
    try {
      read = s.read(onlyIfReady);
    } finally {
      synchronized (lock) {
        inRead = null;
        if (!read && freed == seen) {
          sourceBusy = true; // until sourceFree: that thread queues what it reads, which wakes this one
        }
      }
    }
  }

  // ------------------------------------------------------------- the source

  /**
   * Read {@code s} on the dispatcher thread while it has nothing to run, from now on (in place of
   * a source attached before, whose session ended); false if the dispatcher stopped.
   */
  boolean attach(Source s) {
    Source old;
    synchronized (lock) {
      if (stopped) {
        return false;
      }
      old = source;
      if (old == s) {
        return true;
      }
      source = s;
      sourceBusy = false;
      lock.notifyAll(); // the thread, waiting with no source until now
      wakeFromRead(); // blocked in the old source's read, it reads the new one
    }
    if (old != null) {
      old.dispatched(null);
    }
    s.dispatched(this);
    return true;
  }

  /** A thread let the source go: the dispatcher, waiting because that thread read it, reads again. */
  void sourceFree() {
    synchronized (lock) {
      freed++;
      if (sourceBusy) {
        sourceBusy = false;
        lock.notifyAll();
      }
    }
  }

  /** The source this dispatcher reads, or null (for tests and diagnostics). */
  Source source() {
    return source;
  }

  /** System.nanoTime() at the start of the call running now; 0 between calls (the standby's watch). */
  long callStarted() {
    return callStarted;
  }

  /** System.nanoTime() when the last call returned (the standby sleeps once the dispatcher was idle a while). */
  long lastCallEnded() {
    return lastCallEnded;
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
      wakeFromRead();
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
