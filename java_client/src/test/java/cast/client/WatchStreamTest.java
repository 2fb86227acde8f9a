package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import java.util.List;
import java.util.Map;
import org.junit.jupiter.api.Test;

/**
 * Where a watch resumes after its Watch stream broke: per SA, right after the newest
 * revision it (or its stream) got, never before, and only for the SAs it covers
 * (docs/client-protocol.md, "Reconnection"). A real server restarted under a watching
 * Java component: tests/interop/test_java_reliability.py.
 */
class WatchStreamTest {
  static WatchStream.Watch watch(Map<String, Long> firstStarts, ChangeFilter... filters) {
    return new WatchStream.Watch(
        7, java.util.Arrays.stream(filters).map(Conversions::filter).toList(), firstStarts,
        cast.v1.Delivery.DELIVERY_QUEUE);
  }

  @Test
  void aFirstCreateStartsWhereTheCallerSaid() {
    WatchStream.Watch w = watch(Map.of("vision", 5L), Filters.operationFilter().inSubarchitecture("vision"));
    assertFalse(w.isCreated());
    assertEquals(Map.of("vision", 5L), w.starts(Map.of("vision", 100L)), "the stream's progress does not count yet");
  }

  @Test
  void aResumeStartsAfterTheNewestRevisionSeenAndNeverGoesBack() {
    WatchStream.Watch w = watch(Map.of(), Filters.operationFilter().inSubarchitecture("vision"));
    // Created when the WMs were at vision 3, motor 9: it has seen vision up to 3.
    w.created(Map.of("vision", 3L, "motor", 9L));
    assertTrue(w.isCreated());
    assertEquals(Map.of("vision", 4L), w.starts(Map.of()), "only the SAs the watch covers");
    // Events up to revision 7 came on the stream: resume after them.
    assertEquals(Map.of("vision", 8L), w.starts(Map.of("vision", 7L)));
    // A later resume of a new stream that has seen nothing yet still starts at 8.
    assertEquals(Map.of("vision", 8L), w.starts(Map.of()));
    // A confirmation of the resume does not move the watch back to the server's revision then.
    w.created(Map.of("vision", 2L));
    assertEquals(Map.of("vision", 8L), w.starts(Map.of()));
  }

  @Test
  void aWatchOfEverySaCoversEverySaOfTheServerAndKeepsItsFirstStarts() {
    WatchStream.Watch w = watch(Map.of("motor", 4L), Filters.globalTypeFilter("cast.testing.Counter"));
    w.created(Map.of("vision", 10L, "motor", 20L));
    // vision from the revision at creation; motor from the start the caller asked for (4), so up to 3.
    assertEquals(Map.of("vision", 11L, "motor", 4L), w.starts(Map.of()));
    assertEquals(List.of(), w.filters.stream().map(f -> f.getSubarchitecture()).filter(s -> !s.isEmpty()).toList());
  }
}
