package cast.client;

import cast.v1.DecisionsRequest;
import io.grpc.Metadata;
import io.grpc.Status;
import io.grpc.stub.ClientCallStreamObserver;
import io.grpc.stub.ClientResponseObserver;
import java.util.function.Consumer;
import java.util.logging.Logger;

/**
 * A managed component's {@code TaskManager.Decisions} stream on its own SA's server
 * (docs/client-protocol.md, start-up step 4): every decision about its tasks, also
 * those the Propose answer already carried, so that each hook runs once, from here.
 * When the stream breaks it is opened again with backoff; tasks of a lost session are
 * gone with it, and the server sends the decisions of the new one.
 */
final class DecisionStream {
  private static final Logger LOG = Logger.getLogger("cast.client");

  private final GrpcTransport transport;
  private final GrpcServer server;
  private final Consumer<Task> sink;
  private final Backoff backoff = new Backoff();
  private volatile ClientCallStreamObserver<DecisionsRequest> call;
  private volatile boolean closed;

  /** Opens the stream to {@code server}; decisions go to {@code sink}, in the order they came. */
  DecisionStream(GrpcTransport transport, GrpcServer server, Consumer<Task> sink) {
    this.transport = transport;
    this.server = server;
    this.sink = sink;
    open();
  }

  private void open() {
    if (closed || transport.isClosing()) {
      return;
    }
    server.tmAsync.decisions(
        DecisionsRequest.getDefaultInstance(),
        new ClientResponseObserver<DecisionsRequest, cast.v1.Task>() {
          @Override
          public void beforeStart(ClientCallStreamObserver<DecisionsRequest> requests) {
            call = requests;
          }

          @Override
          public void onNext(cast.v1.Task task) {
            backoff.reset();
            sink.accept(Conversions.task(task));
          }

          @Override
          public void onError(Throwable t) {
            ended(Status.fromThrowable(t), Status.trailersFromThrowable(t));
          }

          @Override
          public void onCompleted() {
            ended(Status.UNAVAILABLE.withDescription("the task manager ended the decision stream"), null);
          }
        });
  }

  /** The stream ended with {@code status}; {@code trailers} (null for none) may name a precise error. */
  private void ended(Status status, Metadata trailers) {
    if (closed || transport.isClosing()) {
      return;
    }
    if (!GrpcTransport.TRANSIENT.contains(status.getCode())) {
      transport.watchErrors().accept(Errors.fromStatus(status, trailers), -1);
      return;
    }
    long delay = backoff.nextMillis();
    LOG.warning("decision stream broke (" + status.getCode() + "); opening it again in " + delay + " ms");
    transport.schedule(
        () -> {
          server.channel.resetConnectBackoff();
          open();
        },
        delay);
  }

  /** End the stream (the component is closing). */
  void close() {
    closed = true;
    var c = call;
    if (c != null) {
      c.cancel("component closing", null);
    }
  }
}
