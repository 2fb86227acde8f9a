package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.testing.CastTesting.Counter;
import java.time.Duration;
import java.util.Map;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.TimeUnit;
import org.junit.jupiter.api.AfterEach;
import org.junit.jupiter.api.BeforeEach;
import org.junit.jupiter.api.Test;

/** A Connection has the calls of a component and ends its session on close (against the in-process fake). */
class ConnectionTest {
  static int counter;
  String name;
  FakeCast fake;

  @BeforeEach
  void setUp() throws Exception {
    name = "connection-" + (++counter) + "-" + System.nanoTime();
    fake = new FakeCast(name, Map.of("vision", ""));
  }

  @AfterEach
  void tearDown() {
    fake.close();
  }

  Connection open() {
    // The fake takes the token for the component id.
    LaunchContract contract = new LaunchContract(name, "script-x", "vision", "script-x", Args.empty());
    return new Connection(new GrpcTransport(contract, FakeCast.channels(), Duration.ofSeconds(5)));
  }

  @Test
  void hasTheCallsOfAComponentAndEndsItsSessionOnClose() throws Exception {
    try (Connection wm = open()) {
      assertEquals("script-x", wm.componentId());
      assertEquals("vision", wm.subarchitecture());
      assertEquals("unmanaged", fake.registrations.get(0).getKind());
      assertEquals("java", fake.registrations.get(0).getLanguage());
      assertTrue(
          ComponentTest.eventually(
              () ->
                  fake.beats.stream()
                      .anyMatch(b -> b.getState() == cast.v1.ComponentState.COMPONENT_STATE_RUNNING),
              Duration.ofSeconds(5)),
          "a connection is reported RUNNING from the start");

      CompletableFuture<String> seen = new CompletableFuture<>();
      wm.onChange(
          Filters.localTypeFilter(Counter.class, Operation.ADD).withEntry(),
          change -> seen.complete(change.entry(Counter.class).value().getWriter()));
      String id = wm.newId();
      assertTrue(id.startsWith("script-x:"), id);
      wm.add(id, Counter.newBuilder().setWriter("script").build());
      assertEquals("script", wm.get(id, Counter.class).getWriter());
      assertTrue(wm.exists(id));
      assertEquals("script", seen.get(10, TimeUnit.SECONDS));
      try (LockGuard guard = wm.lock(id, LockMode.O)) {
        assertEquals("script-x", fake.lockHolders.get("vision/" + id));
      }
      assertNull(fake.lockHolders.get("vision/" + id));
      wm.deleteEntry(id);
      assertFalse(wm.exists(id));
    }
    assertTrue(
        ComponentTest.eventually(() -> fake.endedSessions.size() == 1, Duration.ofSeconds(5)),
        "closing ends the session");
  }
}
