package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.v1.DescribeSystemRequest;
import cast.v1.DirectoryGrpc;
import cast.v1.InspectionGrpc;
import cast.v1.ReportRequest;
import cast.v1.ReportResponse;
import cast.v1.SystemDescription;
import io.grpc.Contexts;
import io.grpc.Metadata;
import io.grpc.Server;
import io.grpc.ServerCall;
import io.grpc.ServerCallHandler;
import io.grpc.ServerInterceptor;
import io.grpc.ServerInterceptors;
import io.grpc.Status;
import io.grpc.inprocess.InProcessChannelBuilder;
import io.grpc.inprocess.InProcessServerBuilder;
import io.grpc.stub.StreamObserver;
import java.time.Duration;
import java.util.List;
import java.util.concurrent.ConcurrentLinkedQueue;
import java.util.concurrent.CopyOnWriteArrayList;
import org.junit.jupiter.api.AfterEach;
import org.junit.jupiter.api.Test;

/**
 * {@link Component#report}: the call reaches the transport as given, on a component and
 * on a script's {@link Connection}; over gRPC it is Inspection.Report with the token,
 * and a refusal is the named error with the server's message. The aggregates a server
 * keeps are checked against real servers in tests/interop/test_metrics_interop.py.
 */
class ReportTest extends WithFakeMemory {
  static final class Plain extends UnmanagedComponent {}

  @Test
  void aComponentReportsThroughItsTransport() {
    Plain c = connect(new Plain(), "quizzer", "language");
    c.report("answers_correct", 1);
    c.report("answer_time_s", 0.25);
    c.report("answer_time_s", Double.NaN); // the server decides what is a bad value
    assertEquals(
        List.of("answers_correct 1.0", "answer_time_s 0.25", "answer_time_s NaN"), FakeTransport.of(c).reports);
  }

  @Test
  void aRefusalIsTheNamedErrorWithTheServersMessage() {
    Plain c = connect(new Plain(), "quizzer", "language");
    FakeTransport.of(c).reportError = new ResourceExhaustedError("too many names");
    ResourceExhaustedError e = assertThrows(ResourceExhaustedError.class, () -> c.report("one-too-many", 1));
    assertEquals("too many names", e.getMessage());
  }

  @Test
  void anUnconnectedComponentSaysHowToConnectIt() {
    IllegalStateException e = assertThrows(IllegalStateException.class, () -> new Plain().report("x", 1));
    assertTrue(e.getMessage().contains("is not connected"), e.getMessage());
  }

  @Test
  void aScriptsConnectionReportsToo() {
    FakeTransport fake = new FakeTransport(memory, new Identity("script-x", "vision", true));
    try (Connection wm = new Connection(fake, who -> {})) {
      wm.report("done", 2);
    }
    assertEquals(List.of("done 2.0"), fake.reports);
  }

  // ------------------------------------------------------------ over gRPC

  private final ConcurrentLinkedQueue<Status> answers = new ConcurrentLinkedQueue<>();
  private final List<ReportRequest> requests = new CopyOnWriteArrayList<>();
  private final List<String> tokens = new CopyOnWriteArrayList<>();
  private Server server;
  private GrpcTransport transport;

  private static final Metadata.Key<String> AUTHORIZATION =
      Metadata.Key.of("authorization", Metadata.ASCII_STRING_MARSHALLER);

  private GrpcTransport grpc() throws Exception {
    DirectoryGrpc.DirectoryImplBase directory =
        new DirectoryGrpc.DirectoryImplBase() {
          @Override
          public void describeSystem(DescribeSystemRequest req, StreamObserver<SystemDescription> out) {
            out.onNext(SystemDescription.newBuilder().setName("t").build());
            out.onCompleted();
          }
        };
    InspectionGrpc.InspectionImplBase inspection =
        new InspectionGrpc.InspectionImplBase() {
          @Override
          public void report(ReportRequest req, StreamObserver<ReportResponse> out) {
            requests.add(req);
            Status answer = answers.poll();
            if (answer == null) {
              out.onNext(ReportResponse.getDefaultInstance());
              out.onCompleted();
            } else {
              out.onError(answer.asRuntimeException());
            }
          }
        };
    ServerInterceptor recordToken =
        new ServerInterceptor() {
          @Override
          public <Q, R> ServerCall.Listener<Q> interceptCall(
              ServerCall<Q, R> call, Metadata headers, ServerCallHandler<Q, R> next) {
            tokens.add(String.valueOf(headers.get(AUTHORIZATION)));
            return Contexts.interceptCall(io.grpc.Context.current(), call, headers, next);
          }
        };
    String name = InProcessServerBuilder.generateName();
    server =
        InProcessServerBuilder.forName(name)
            .addService(directory)
            .addService(ServerInterceptors.intercept(inspection, recordToken))
            .build()
            .start();
    transport =
        new GrpcTransport(
            new LaunchContract("in-process", "quizzer", "language", "tok.sig", Args.empty()),
            endpoint -> InProcessChannelBuilder.forName(name).build(),
            Duration.ofSeconds(5));
    return transport;
  }

  @AfterEach
  void closeGrpc() {
    if (transport != null) {
      transport.close();
    }
    if (server != null) {
      server.shutdownNow();
    }
  }

  @Test
  void overGrpcItSendsTheNameAndValueWithTheToken() throws Exception {
    grpc().report("answer_time_s", 1.5);
    assertEquals(1, requests.size());
    assertEquals("answer_time_s", requests.get(0).getName());
    assertEquals(1.5, requests.get(0).getValue());
    assertEquals(List.of("Bearer tok.sig"), tokens);
  }

  @Test
  void overGrpcInvalidArgumentAndResourceExhaustedAreTheirNamedErrors() throws Exception {
    answers.add(Status.INVALID_ARGUMENT.withDescription("report 'x': the value must be a finite number, got nan"));
    answers.add(Status.RESOURCE_EXHAUSTED.withDescription("already reports 256 names"));
    GrpcTransport t = grpc();
    InvalidArgumentError bad = assertThrows(InvalidArgumentError.class, () -> t.report("x", Double.NaN));
    assertEquals("report 'x': the value must be a finite number, got nan", bad.getMessage());
    ResourceExhaustedError many = assertThrows(ResourceExhaustedError.class, () -> t.report("y", 1));
    assertEquals("already reports 256 names", many.getMessage());
    assertTrue(Double.isNaN(requests.get(0).getValue()));
  }
}
