package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import java.time.Duration;
import java.util.ArrayList;
import java.util.Collections;
import java.util.List;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicBoolean;
import java.util.logging.Logger;
import org.junit.jupiter.api.Test;

class DispatcherTest {
  static final Logger LOG = Logger.getLogger("cast.test");

  @Test
  void runsCallsInOrderOnOneThreadAndSurvivesFailures() throws Exception {
    Dispatcher d = new Dispatcher("t", 100, LOG);
    List<Integer> seen = Collections.synchronizedList(new ArrayList<>());
    List<Thread> threads = Collections.synchronizedList(new ArrayList<>());
    for (int i = 0; i < 50; i++) {
      int n = i;
      d.submit(
          () -> {
            threads.add(Thread.currentThread());
            if (n == 10) {
              throw new IllegalStateException("one bad callback");
            }
            seen.add(n);
          });
    }
    assertTrue(d.drain(Duration.ofSeconds(5)));
    assertEquals(49, seen.size());
    for (int i = 1; i < seen.size(); i++) {
      assertTrue(seen.get(i - 1) < seen.get(i));
    }
    assertEquals(1, threads.stream().distinct().count());
    assertSame(d.thread(), threads.get(0));
    d.stop(Duration.ofSeconds(1));
    assertFalse(d.thread().isAlive());
  }

  @Test
  void aFullQueueHoldsUpBlockingSubmitsUntilThereIsRoom() throws Exception {
    Dispatcher d = new Dispatcher("full", 2, LOG);
    CountDownLatch gate = new CountDownLatch(1);
    d.submit(
        () -> {
          try {
            gate.await();
          } catch (InterruptedException e) {
            Thread.currentThread().interrupt();
          }
        });
    d.submitBlocking(() -> {}); // second: fits
    AtomicBoolean third = new AtomicBoolean();
    Thread reader =
        new Thread(
            () -> {
              try {
                d.submitBlocking(() -> {});
                third.set(true);
              } catch (InterruptedException e) {
                Thread.currentThread().interrupt();
              }
            });
    reader.start();
    reader.join(300);
    assertTrue(reader.isAlive(), "the third submit waits while two calls are pending");
    assertFalse(third.get());
    d.submit(() -> {}); // hooks never wait
    assertEquals(3, d.pending());
    gate.countDown();
    reader.join(5000);
    assertTrue(third.get());
    assertTrue(d.drain(Duration.ofSeconds(5)));
    assertEquals(0, d.pending());
  }

  @Test
  void theDispatcherThreadNeverWaitsForItself() throws Exception {
    Dispatcher d = new Dispatcher("self", 1, LOG);
    CountDownLatch done = new CountDownLatch(1);
    List<Boolean> drained = new ArrayList<>();
    d.submit(
        () -> {
          try {
            d.submitBlocking(done::countDown); // full (this call is pending): must not wait for itself
            drained.add(d.drain(Duration.ofSeconds(1)));
          } catch (InterruptedException e) {
            Thread.currentThread().interrupt();
          }
        });
    assertTrue(done.await(5, TimeUnit.SECONDS));
    assertEquals(List.of(false), drained);
  }

  @Test
  void capacityMustBePositive() {
    assertThrows(InvalidArgumentError.class, () -> new Dispatcher("bad", 0, LOG));
  }
}
