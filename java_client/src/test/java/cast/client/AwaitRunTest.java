package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.v1.AwaitRunRequest;
import cast.v1.AwaitRunResponse;
import cast.v1.DescribeSystemRequest;
import cast.v1.DirectoryGrpc;
import cast.v1.SubarchitectureInfo;
import cast.v1.SystemDescription;
import io.grpc.Server;
import io.grpc.Status;
import io.grpc.inprocess.InProcessChannelBuilder;
import io.grpc.inprocess.InProcessServerBuilder;
import io.grpc.stub.StreamObserver;
import java.time.Duration;
import java.util.List;
import java.util.concurrent.ConcurrentLinkedQueue;
import java.util.concurrent.CopyOnWriteArrayList;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.TimeUnit;
import org.junit.jupiter.api.AfterEach;
import org.junit.jupiter.api.Test;

/**
 * The start barrier's long poll ({@link GrpcTransport#awaitRun}) against an in-process
 * directory that answers AwaitRun as scripted: "hold" (no answer: the caller's 1 s
 * deadline ends the call), a status code name, or "OK" (released).
 */
class AwaitRunTest {
  private final ConcurrentLinkedQueue<String> script = new ConcurrentLinkedQueue<>();
  private final List<Long> callTimes = new CopyOnWriteArrayList<>(); // nanoTime of each AwaitRun
  private final CountDownLatch called = new CountDownLatch(1);
  private Server server;
  private GrpcTransport transport;

  private final class Directory extends DirectoryGrpc.DirectoryImplBase {
    @Override
    public void describeSystem(DescribeSystemRequest req, StreamObserver<SystemDescription> out) {
      out.onNext(
          SystemDescription.newBuilder()
              .setName("t")
              .addSubarchitectures(SubarchitectureInfo.newBuilder().setName("vision"))
              .build());
      out.onCompleted();
    }

    @Override
    public void awaitRun(AwaitRunRequest req, StreamObserver<AwaitRunResponse> out) {
      callTimes.add(System.nanoTime());
      called.countDown();
      String next = script.poll();
      if (next == null || next.equals("hold")) {
        return; // the barrier is held: the caller's deadline ends the call
      }
      if (next.equals("OK")) {
        out.onNext(AwaitRunResponse.getDefaultInstance());
        out.onCompleted();
      } else {
        out.onError(Status.fromCode(Status.Code.valueOf(next)).withDescription("scripted").asRuntimeException());
      }
    }
  }

  private GrpcTransport connect(String... answers) throws Exception {
    script.addAll(List.of(answers));
    String name = InProcessServerBuilder.generateName();
    server = InProcessServerBuilder.forName(name).addService(new Directory()).build().start();
    transport =
        new GrpcTransport(
            new LaunchContract("in-process", "c", "vision", "tok.sig", Args.empty()),
            endpoint -> InProcessChannelBuilder.forName(name).build(),
            Duration.ofSeconds(5));
    return transport;
  }

  @AfterEach
  void close() {
    if (transport != null) {
      transport.close();
    }
    if (server != null) {
      server.shutdownNow();
    }
  }

  private static Transport.StopWait never() {
    return timeout -> {
      Thread.sleep(timeout.toMillis());
      return false;
    };
  }

  @Test
  void callsAgainAfterItsDeadlineAndAfterUnavailableUntilReleased() throws Exception {
    GrpcTransport t = connect("hold", "UNAVAILABLE", "DEADLINE_EXCEEDED", "OK");
    long start = System.nanoTime();
    assertTrue(t.awaitRun(never()));
    assertEquals(4, callTimes.size(), "held, away, deadline, released");
    long firstGap = TimeUnit.NANOSECONDS.toMillis(callTimes.get(1) - callTimes.get(0));
    assertTrue(firstGap >= 900 && firstGap < 3_000, "a held call ends at its 1 s deadline, not sooner: " + firstGap);
    assertTrue(TimeUnit.NANOSECONDS.toMillis(System.nanoTime() - start) < 5_000);
  }

  @Test
  void anyOtherErrorFailsTheStart() throws Exception {
    GrpcTransport t = connect("PERMISSION_DENIED");
    PermissionDeniedError e = assertThrows(PermissionDeniedError.class, () -> t.awaitRun(never()));
    assertEquals("scripted", e.getMessage());
  }

  @Test
  void aStopRequestEndsTheWaitWithoutRunning() throws Exception {
    GrpcTransport t = connect(); // held for ever
    CountDownLatch stop = new CountDownLatch(1);
    new Thread(() -> {
      try {
        called.await(5, TimeUnit.SECONDS);
      } catch (InterruptedException e) {
        Thread.currentThread().interrupt();
      }
      stop.countDown();
    }).start();
    long start = System.nanoTime();
    assertFalse(t.awaitRun(timeout -> stop.await(timeout.toNanos(), TimeUnit.NANOSECONDS)));
    assertTrue(TimeUnit.NANOSECONDS.toMillis(System.nanoTime() - start) < 3_000, "seen within a poll");
  }

  @Test
  void aStopRequestedBeforeTheWaitMakesNoCall() throws Exception {
    GrpcTransport t = connect("OK");
    assertFalse(t.awaitRun(timeout -> true));
    assertEquals(0, callTimes.size());
  }
}
