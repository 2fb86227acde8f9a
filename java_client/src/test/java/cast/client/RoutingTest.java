package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.testing.CastTesting.Counter;
import java.time.Duration;
import java.util.ArrayList;
import java.util.Collections;
import java.util.List;
import java.util.Map;
import org.junit.jupiter.api.Test;

/** Routing by SA through DescribeSystem (docs/client-protocol.md, start-up step 2). */
class RoutingTest {
  static final class Plain extends UnmanagedComponent {}

  @Test
  void eachSubarchitectureGoesToItsServer() throws Exception {
    String a = "route-a-" + System.nanoTime();
    String b = "route-b-" + System.nanoTime();
    // The directory (a) hosts vision itself (its own endpoint, or empty) and sends motor to b.
    Map<String, String> layout = Map.of("vision", a, "language", "", "motor", b);
    try (FakeCast dirServer = new FakeCast(a, layout);
        FakeCast motorServer = new FakeCast(b, layout)) {
      Plain c = FakeCast.connect(new Plain(), a, "c1", "vision");
      try {
        c.add("v", Counter.getDefaultInstance());
        c.add("l", Counter.getDefaultInstance(), "language");
        c.add("m", Counter.getDefaultInstance(), "motor");
        c.exists("x", "nowhere"); // unknown SA: the directory's server answers
        assertEquals(List.of("Add vision/v", "Add language/l", "Exists nowhere/x"), dirServer.calls);
        assertEquals(List.of("Add motor/m"), motorServer.calls);
        // A session on every server used; schemas registered with every server.
        assertEquals(1, dirServer.registrations.size());
        assertEquals(1, motorServer.registrations.size());
        assertEquals(1, dirServer.schemaRequests.size());
        assertEquals(1, motorServer.schemaRequests.size());
        // A global filter watches every server; events of both arrive on one dispatcher.
        List<String> seen = Collections.synchronizedList(new ArrayList<>());
        c.onChange(Filters.globalTypeFilter(Counter.class), ch -> seen.add(ch.subarchitecture() + "/" + ch.id()));
        c.add("m2", Counter.getDefaultInstance(), "motor");
        c.add("v2", Counter.getDefaultInstance());
        assertTrue(ComponentTest.eventually(() -> seen.size() == 2, Duration.ofSeconds(5)));
        // Order is kept per server (per WM), not across servers.
        assertEquals(java.util.Set.of("motor/m2", "vision/v2"), java.util.Set.copyOf(seen));
        assertEquals(1, dirServer.watchStreams.size());
        assertEquals(1, motorServer.watchStreams.size());
        // A local filter watches only the own SA's server.
        c.onChange(Filters.localTypeFilter(Counter.class), ch -> {});
        assertEquals(List.of(1), List.of(dirServer.watchStreams.size()));
        assertEquals(1, motorServer.watchStreams.get(0).watches.size());
        assertEquals(2, dirServer.watchStreams.get(0).watches.size());
      } finally {
        c.close();
      }
    }
  }
}
