package cast.client;

import io.grpc.CallOptions;
import io.grpc.Channel;
import io.grpc.ClientCall;
import io.grpc.ClientInterceptor;
import io.grpc.ForwardingClientCall;
import io.grpc.MethodDescriptor;
import java.io.BufferedReader;
import java.io.IOException;
import java.io.InputStreamReader;
import java.nio.charset.StandardCharsets;
import java.nio.file.Files;
import java.nio.file.Path;
import java.time.Duration;
import java.util.List;
import java.util.concurrent.CopyOnWriteArrayList;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicInteger;

/**
 * A real CAST server for the JUnit tests that need one: {@code cast serve} from the
 * repository's {@code .venv} (made by {@code make setup proto}, which {@code make test-java}
 * runs first) on port 0 of 127.0.0.1, as tests/conftest.py starts them, hosting the SAs
 * vision and motor in memory. Components connect to it as {@link Connection}s over the real
 * {@link GrpcTransport}, with tokens minted from its secret.
 */
final class RealServer implements AutoCloseable {
  static final String SECRET = "junit-secret-0123456789abcdef-0123456789";

  /**
   * The gRPC methods a connection called, by full name ("cast.v1.WorkingMemory/Write"), in
   * order, and the messages it sent on its Write calls.
   */
  static final class Calls implements ClientInterceptor {
    final List<String> methods = new CopyOnWriteArrayList<>();
    final AtomicInteger writeMessages = new AtomicInteger();

    @Override
    public <Q, R> ClientCall<Q, R> interceptCall(MethodDescriptor<Q, R> method, CallOptions options, Channel next) {
      methods.add(method.getFullMethodName());
      ClientCall<Q, R> call = next.newCall(method, options);
      if (!method.getFullMethodName().equals("cast.v1.WorkingMemory/Write")) {
        return call;
      }
      return new ForwardingClientCall.SimpleForwardingClientCall<Q, R>(call) {
        @Override
        public void sendMessage(Q message) {
          writeMessages.incrementAndGet();
          super.sendMessage(message);
        }
      };
    }

    /** How many calls of {@code method} ("WorkingMemory/Write") were made. */
    long count(String method) {
      return methods.stream().filter(m -> m.equals("cast.v1." + method)).count();
    }
  }

  private final Path dir;
  private final Path config;
  private Process process;
  private String endpoint;
  private final List<String> log = new CopyOnWriteArrayList<>();

  /** Starts a server on a free port. */
  RealServer() throws IOException {
    dir = Files.createTempDirectory("cast-junit-");
    config = dir.resolve("system.yaml");
    Files.writeString(config, "system: junit\nsubarchitectures:\n  vision: {}\n  motor: {}\n");
    start("127.0.0.1:0");
  }

  /** The repository's root: the nearest directory up from here that holds proto/cast/v1. */
  static Path repository() {
    for (Path p = Path.of("").toAbsolutePath(); p != null; p = p.getParent()) {
      if (Files.isDirectory(p.resolve("proto/cast/v1"))) {
        return p;
      }
    }
    throw new IllegalStateException("run the tests from inside the repository (no proto/cast/v1 above " + Path.of("").toAbsolutePath() + ")");
  }

  private void start(String listen) throws IOException {
    Path cast = repository().resolve(".venv/bin/cast");
    if (!Files.isExecutable(cast)) {
      throw new IllegalStateException(
          "these tests run a real server, " + cast + ", which is missing: run `make setup proto` first"
              + " (`make test-java` does)");
    }
    ProcessBuilder pb = new ProcessBuilder(cast.toString(), "serve", config.toString(), "--listen", listen);
    pb.directory(dir.toFile()).redirectErrorStream(true);
    pb.environment().put("CAST_SECRET", SECRET);
    process = pb.start();
    BufferedReader out = new BufferedReader(new InputStreamReader(process.getInputStream(), StandardCharsets.UTF_8));
    String first = out.readLine();
    if (first == null || !first.startsWith("listening on ")) {
      process.destroyForcibly();
      StringBuilder rest = new StringBuilder();
      for (String line; (line = out.readLine()) != null; ) {
        rest.append(line).append('\n');
      }
      throw new IllegalStateException("the server did not start: " + first + "\n" + rest);
    }
    endpoint = first.substring("listening on ".length()).trim();
    Thread drain =
        new Thread(
            () -> {
              try {
                for (String line; (line = out.readLine()) != null; ) {
                  log.add(line);
                }
              } catch (IOException e) {
                // the server ended
              }
            },
            "cast-junit-server-log");
    drain.setDaemon(true);
    drain.start();
  }

  /** host:port of the server. */
  String endpoint() {
    return endpoint;
  }

  /** What the server printed after its first line. */
  List<String> log() {
    return log;
  }

  /** A token for a component, signed with the server's secret; it expires at {@code exp} (seconds since the epoch; 0: never). */
  static String token(String id, String sa, boolean privileged, long exp) {
    long now = System.currentTimeMillis() / 1000;
    if (exp == 0) {
      return Tokens.mint(SECRET.getBytes(StandardCharsets.UTF_8), new Identity(id, sa, privileged), now);
    }
    String claims =
        "{\"c\":" + Tokens.jsonString(id) + ",\"s\":" + Tokens.jsonString(sa) + ",\"p\":" + privileged + ",\"iat\":"
            + now + ",\"exp\":" + exp + "}";
    String input = Tokens.HEADER + "." + Tokens.base64Url(claims.getBytes(StandardCharsets.UTF_8));
    return input + "." + Tokens.signHs256(input, SECRET.getBytes(StandardCharsets.UTF_8));
  }

  /** A connection as component {@code id} of {@code sa}; {@code calls} (may be null) sees its gRPC calls. */
  Connection connect(String id, String sa, boolean privileged, Calls calls) {
    return connect(new LaunchContract(endpoint, id, sa, token(id, sa, privileged, 0), Args.empty()), calls);
  }

  /** A connection with {@code contract} (its endpoint this server's). */
  Connection connect(LaunchContract contract, Calls calls) {
    return connect(contract, calls, true);
  }

  /**
   * A connection as {@link #connect(String, String, boolean, Calls)}; {@code sharedMemory} false:
   * as with {@code CAST_SHARED_MEMORY=off} for it alone, so that its writes go on the gRPC Write
   * stream (with a session they go on its socket).
   */
  Connection connect(String id, String sa, boolean privileged, Calls calls, boolean sharedMemory) {
    return connect(new LaunchContract(endpoint, id, sa, token(id, sa, privileged, 0), Args.empty()), calls, sharedMemory);
  }

  /** A connection with {@code contract}, with shared memory or not ({@link #connect(String, String, boolean, Calls, boolean)}). */
  Connection connect(LaunchContract contract, Calls calls, boolean sharedMemory) {
    ClientInterceptor[] seen = calls == null ? new ClientInterceptor[0] : new ClientInterceptor[] {calls};
    GrpcTransport transport =
        new GrpcTransport(contract, e -> GrpcServer.channel(e, null, seen), GrpcTransport.DEFAULT_CALL_TIMEOUT);
    if (!sharedMemory) {
      for (GrpcServer s : transport.allServers()) { // before any use: no session was opened yet
        s.shared =
            new SharedLink(
                s.endpoint,
                () -> "",
                within -> {
                  throw new AssertionError("a client with shared memory off does not ask where it is");
                },
                name -> name.equals(SharedLink.ENV) ? "off" : null);
      }
    }
    return new Connection(transport, who -> {});
  }

  /** WRITES frames {@code c} sent so far on its live session with the server of SA vision (0 without one). */
  static long writeFrames(Connection c) {
    SharedSession s = ((GrpcTransport) c.transport()).server("vision").shared.current();
    return s == null ? 0 : s.writes().framesSent.get();
  }

  /** SIGSTOP: the server takes requests into its socket and answers none, until killed. */
  void pause() throws IOException, InterruptedException {
    new ProcessBuilder("kill", "-STOP", Long.toString(process.pid())).inheritIO().start().waitFor();
  }

  /** SIGKILL: the server is gone at once, its connections broken. */
  void kill() throws InterruptedException {
    process.destroyForcibly();
    process.waitFor(10, TimeUnit.SECONDS);
  }

  /** Start again on the same address (after {@link #kill}): an empty memory, the same endpoint. */
  void restart() throws IOException {
    start(endpoint);
  }

  @Override
  public void close() throws InterruptedException, IOException {
    process.destroy(); // SIGTERM: the server stops cleanly
    if (!process.waitFor(10, TimeUnit.SECONDS)) {
      process.destroyForcibly();
      process.waitFor(10, TimeUnit.SECONDS);
    }
    try (var files = Files.walk(dir)) {
      for (Path p : files.sorted(java.util.Comparator.reverseOrder()).toList()) {
        Files.deleteIfExists(p);
      }
    }
  }

  /** Wait until {@code condition} holds, failing after {@code timeout} (a guard, not a measurement). */
  static void waitFor(java.util.function.BooleanSupplier condition, Duration timeout, String what)
      throws InterruptedException {
    long deadline = System.nanoTime() + timeout.toNanos();
    while (!condition.getAsBoolean()) {
      if (System.nanoTime() > deadline) {
        throw new AssertionError("timed out waiting for " + what);
      }
      Thread.sleep(10);
    }
  }
}
