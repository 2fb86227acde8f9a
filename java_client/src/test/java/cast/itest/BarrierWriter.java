package cast.itest;

import cast.client.Args;
import cast.client.UnmanagedComponent;
import com.google.protobuf.Int64Value;

/**
 * A start-barrier writer (tests/interop/test_start_barrier.py), the twin of BarrierWriter in
 * tests/orchestrator/components/barrier_components.py: configured privileged with args
 * {"sa": SA, "count": N}; first thing in run() it adds {@code <id>-0} .. {@code <id>-<N-1>}
 * (Int64Value i), then {@code <id>-end} (Int64Value N), to SA {@code sa}.
 */
public class BarrierWriter extends UnmanagedComponent {
  private String sa;
  private int count;

  @Override
  public void configure(Args args) {
    if (!args.has("sa") || !args.has("count")) {
      throw new IllegalArgumentException("BarrierWriter needs args {\"sa\": SA, \"count\": N}, got " + args);
    }
    sa = args.getString("sa", "");
    count = args.getInt("count", 0);
  }

  @Override
  public void run() throws Exception {
    for (int i = 0; i < count; i++) {
      add(componentId() + "-" + i, Int64Value.of(i), sa);
    }
    add(componentId() + "-end", Int64Value.of(count), sa);
    waitForStop();
  }
}
