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
  void theHighestPriorityPendingCallRunsFirstInArrivalOrderWithinOne() throws Exception {
    Dispatcher d = new Dispatcher("prio", 100, LOG);
    CountDownLatch busy = new CountDownLatch(1);
    CountDownLatch release = new CountDownLatch(1);
    List<String> order = Collections.synchronizedList(new ArrayList<>());
    d.submit(
        () -> {
          busy.countDown();
          try {
            release.await();
          } catch (InterruptedException e) {
            Thread.currentThread().interrupt();
          }
        });
    assertTrue(busy.await(5, TimeUnit.SECONDS));
    d.submit(Priority.LOW, () -> order.add("low 1"));
    d.submit(() -> order.add("hook")); // hooks are MEDIUM
    d.submitBlocking(Priority.HIGH, () -> order.add("high 1"));
    d.submit(Priority.LOW, () -> order.add("low 2"));
    d.submit(Priority.HIGH, () -> order.add("high 2"));
    release.countDown();
    assertTrue(d.drain(Duration.ofSeconds(5)));
    assertEquals(List.of("high 1", "high 2", "hook", "low 1", "low 2"), order);
    d.stop(Duration.ofSeconds(1));
  }

  @Test
  void stopRunsWhatIsQueuedAndDropsWhatComesAfter() throws Exception {
    Dispatcher d = new Dispatcher("stop", 100, LOG);
    CountDownLatch release = new CountDownLatch(1);
    List<String> ran = Collections.synchronizedList(new ArrayList<>());
    d.submit(
        () -> {
          try {
            release.await();
          } catch (InterruptedException e) {
            Thread.currentThread().interrupt();
          }
        });
    d.submit(Priority.LOW, () -> ran.add("queued before"));
    Thread stopper = new Thread(() -> d.stop(Duration.ofSeconds(5)));
    stopper.start();
    assertTrue(eventuallyStopping(d));
    d.submit(() -> ran.add("queued after"));
    release.countDown();
    stopper.join(5000);
    assertFalse(d.thread().isAlive());
    assertEquals(List.of("queued before"), ran);
  }

  private static boolean eventuallyStopping(Dispatcher d) throws InterruptedException {
    // stop() returns only when the thread ends; its flag is set at once
    for (int i = 0; i < 500; i++) {
      if (d.isStopped()) {
        return true;
      }
      Thread.sleep(2);
    }
    return false;
  }

  @Test
  void capacityMustBePositive() {
    assertThrows(InvalidArgumentError.class, () -> new Dispatcher("bad", 0, LOG));
  }
}
