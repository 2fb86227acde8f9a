package cast.client;

import cast.v1.DirectoryGrpc;
import cast.v1.InspectionGrpc;
import cast.v1.TaskManagerGrpc;
import cast.v1.WorkingMemoryGrpc;
import io.grpc.ClientInterceptor;
import io.grpc.Grpc;
import io.grpc.ManagedChannel;
import io.grpc.ManagedChannelBuilder;
import java.util.concurrent.TimeUnit;

/**
 * One server of a system as the gRPC transport reaches it: its channel and a stub per
 * service, each putting the token on every call. Its streams belong to whoever opened
 * them ({@link WriteStream}, {@link WatchStream}, {@link Session}, {@link DecisionStream}). Part of the
 * {@code grpc_transport} role of the client file map (docs/design.md, "Client
 * libraries"), as cpp_client/src/grpc_server.h is: {@link GrpcTransport} routes SAs to
 * these and makes the unary calls.
 */
final class GrpcServer {
  static final int MAX_MESSAGE_BYTES = 64 * 1024 * 1024;

  /** Opens a channel to an endpoint. */
  interface ChannelFactory {
    ManagedChannel open(String endpoint);
  }

  /**
   * A channel to {@code endpoint}, with TLS when {@code tls} is set (never falling back to
   * plaintext); {@code interceptors} see every call (tests count them).
   */
  static ManagedChannel channel(String endpoint, ClientTls tls, ClientInterceptor... interceptors) {
    ManagedChannelBuilder<?> b;
    if (tls == null) {
      b = ManagedChannelBuilder.forTarget(endpoint).usePlaintext();
    } else {
      b = Grpc.newChannelBuilder(endpoint, Credentials.channelCredentials(tls));
      if (!tls.serverName().isEmpty()) {
        b.overrideAuthority(tls.serverName());
      }
    }
    return b.intercept(interceptors)
        .maxInboundMessageSize(MAX_MESSAGE_BYTES)
        // Notice a dead server (and let it notice us) on an idle connection;
        // the server permits pings every 5 s without data.
        .keepAliveTime(10, TimeUnit.SECONDS)
        .keepAliveTimeout(5, TimeUnit.SECONDS)
        .keepAliveWithoutCalls(true)
        .build();
  }

  final String endpoint;
  final ManagedChannel channel;
  final WorkingMemoryGrpc.WorkingMemoryBlockingStub wm;
  final WorkingMemoryGrpc.WorkingMemoryStub wmAsync;
  final TaskManagerGrpc.TaskManagerBlockingStub tm;
  final TaskManagerGrpc.TaskManagerStub tmAsync;
  final DirectoryGrpc.DirectoryBlockingStub dir;
  final DirectoryGrpc.DirectoryStub dirAsync;
  final InspectionGrpc.InspectionBlockingStub insp; // Report: the component's outcomes
  volatile Session session;
  volatile WriteStream writes; // opened by GrpcTransport on the first write to this server
  volatile SharedLink shared; // shared memory with this server on its host (SharedLink.java)

  /** Opens a channel to {@code endpoint} through {@code channels}; {@code credentials} authorise every call. */
  GrpcServer(String endpoint, ChannelFactory channels, Credentials credentials) {
    this.endpoint = endpoint;
    this.channel = channels.open(endpoint);
    ClientInterceptor auth = credentials.interceptor();
    this.wm = WorkingMemoryGrpc.newBlockingStub(channel).withInterceptors(auth);
    this.wmAsync = WorkingMemoryGrpc.newStub(channel).withInterceptors(auth);
    this.tm = TaskManagerGrpc.newBlockingStub(channel).withInterceptors(auth);
    this.tmAsync = TaskManagerGrpc.newStub(channel).withInterceptors(auth);
    this.dir = DirectoryGrpc.newBlockingStub(channel).withInterceptors(auth);
    this.dirAsync = DirectoryGrpc.newStub(channel).withInterceptors(auth);
    this.insp = InspectionGrpc.newBlockingStub(channel).withInterceptors(auth);
  }
}
