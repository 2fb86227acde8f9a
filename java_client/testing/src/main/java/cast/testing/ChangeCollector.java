package cast.testing;

import cast.client.Connection;
import cast.client.WorkingMemoryChange;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.function.Predicate;

/**
 * The changes a watch of its own delivered, in the order they came ({@link
 * LocalSystem#collectChanges}, which registers the watch before it returns).
 */
public final class ChangeCollector implements AutoCloseable {
  private final List<WorkingMemoryChange> collected = new ArrayList<>();
  private Connection watcher;

  ChangeCollector() {}

  void watchWith(Connection connection) {
    this.watcher = connection;
  }

  void collect(WorkingMemoryChange change) {
    synchronized (collected) {
      collected.add(change);
    }
  }

  /** The changes collected so far (a copy). */
  public List<WorkingMemoryChange> changes() {
    synchronized (collected) {
      return List.copyOf(collected);
    }
  }

  /** How many changes came so far. */
  public int size() {
    synchronized (collected) {
      return collected.size();
    }
  }

  /** One line per change collected. */
  public String describe() {
    List<WorkingMemoryChange> all = changes();
    if (all.isEmpty()) {
      return "no changes";
    }
    StringBuilder out = new StringBuilder(all.size() + (all.size() == 1 ? " change:" : " changes:"));
    for (WorkingMemoryChange change : all) {
      out.append("\n  ").append(CastTesting.describeChange(change));
    }
    return out.toString();
  }

  /** {@link #waitForCount(int, Duration)} for 10 s. */
  public List<WorkingMemoryChange> waitForCount(int count) {
    return waitForCount(count, CastTesting.DEFAULT_TIMEOUT);
  }

  /** Waits until at least {@code count} changes came; the first {@code count}. The failure lists those that came. */
  public List<WorkingMemoryChange> waitForCount(int count, Duration timeout) {
    CastTesting.waitFor(() -> size() >= count, timeout, count + (count == 1 ? " change" : " changes"), this::describe);
    return changes().subList(0, count);
  }

  /** {@link #waitForChange(Predicate, Duration, String)} for 10 s. */
  public WorkingMemoryChange waitForChange(Predicate<WorkingMemoryChange> test) {
    return waitForChange(test, CastTesting.DEFAULT_TIMEOUT, "a matching change");
  }

  /** Waits for a change that passes {@code test}; the first one. The failure lists those that came. */
  public WorkingMemoryChange waitForChange(Predicate<WorkingMemoryChange> test, Duration timeout, String what) {
    WorkingMemoryChange[] found = new WorkingMemoryChange[1];
    CastTesting.waitFor(
        () -> {
          for (WorkingMemoryChange change : changes()) {
            if (test.test(change)) {
              found[0] = change;
              return true;
            }
          }
          return false;
        },
        timeout,
        what,
        this::describe);
    return found[0];
  }

  /** Forgets what was collected (collecting goes on). */
  public void clear() {
    synchronized (collected) {
      collected.clear();
    }
  }

  /** Stops collecting (what was collected stays). */
  @Override
  public void close() {
    if (watcher != null) {
      watcher.close();
    }
  }
}
