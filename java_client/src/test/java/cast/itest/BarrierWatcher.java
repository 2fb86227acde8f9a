package cast.itest;

import static cast.client.Filters.operationFilter;

import cast.client.Operation;
import cast.client.UnmanagedComponent;
import cast.client.WorkingMemoryChange;
import com.google.protobuf.Int64Value;
import java.util.HashMap;
import java.util.Map;

/**
 * A start-barrier watcher (tests/interop/test_start_barrier.py), the twin of BarrierWatcher in
 * tests/orchestrator/components/barrier_components.py: watches ADDs to its own SA from start();
 * for {@code <writer>-<n>} counts one for the writer; at {@code <writer>-end} adds
 * {@code seen-<id>-<writer>} (Int64Value: how many of the writer's entries it saw) to its own SA.
 */
public class BarrierWatcher extends UnmanagedComponent {
  private final Map<String, Long> seen = new HashMap<>(); // guarded by this

  @Override
  public void start() {
    onChange(operationFilter(Operation.ADD).local(), this::added);
  }

  private void added(WorkingMemoryChange change) {
    String id = change.id();
    if (id.startsWith("seen-")) {
      return; // another watcher's report
    }
    int dash = id.lastIndexOf('-');
    String writer = dash < 0 ? "" : id.substring(0, dash);
    String rest = id.substring(dash + 1);
    long count;
    synchronized (this) {
      if (!rest.equals("end")) {
        seen.merge(writer, 1L, Long::sum);
        return;
      }
      count = seen.getOrDefault(writer, 0L);
    }
    add("seen-" + componentId() + "-" + writer, Int64Value.of(count));
  }
}
