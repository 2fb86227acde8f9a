package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.testing.CastTesting.Counter;
import java.util.List;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.TimeUnit;
import org.junit.jupiter.api.Test;

/** A Connection has the calls of a component and ends its session on close (against the in-memory fake). */
class ConnectionTest {
  final FakeTransport.Memory memory = new FakeTransport.Memory("vision");

  @Test
  void hasTheCallsOfAComponentAndEndsItsSessionOnClose() throws Exception {
    FakeTransport fake = new FakeTransport(memory, new Identity("script-x", "vision", true));
    try (Connection wm = new Connection(fake, who -> {})) {
      assertEquals("script-x", wm.componentId());
      assertEquals("vision", wm.subarchitecture());
      assertEquals(List.of("java unmanaged"), fake.sessions);
      assertEquals(List.of(ComponentState.RUNNING), fake.reported, "a connection is reported RUNNING from the start");

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
        assertEquals("script-x", memory.lockHolders.get("vision/" + id));
      }
      assertNull(memory.lockHolders.get("vision/" + id));
      wm.deleteEntry(id);
      assertFalse(wm.exists(id));
      assertFalse(fake.closed);
    }
    assertTrue(fake.closed, "closing ends the session");
  }
}
