package cast.testing;

import cast.client.Args;
import cast.client.Cast;
import cast.client.ChangeFilter;
import cast.client.Component;
import cast.client.ConnectOptions;
import cast.client.Connection;
import cast.client.Entry;
import cast.client.Filters;
import cast.client.Identity;
import cast.client.InvalidArgumentError;
import cast.client.LaunchContract;
import cast.client.NotFoundError;
import cast.client.Runner;
import cast.client.Tokens;
import cast.client.UnavailableError;
import cast.v1.DescribeSystemRequest;
import cast.v1.DirectoryGrpc;
import cast.v1.InspectionGrpc;
import cast.v1.ListEntriesRequest;
import cast.v1.ListEntriesResponse;
import cast.v1.SubarchitectureInfo;
import cast.v1.SystemDescription;
import com.google.protobuf.Message;
import io.grpc.ManagedChannel;
import io.grpc.ManagedChannelBuilder;
import io.grpc.Metadata;
import io.grpc.StatusRuntimeException;
import io.grpc.stub.MetadataUtils;
import java.io.IOException;
import java.io.UncheckedIOException;
import java.nio.charset.StandardCharsets;
import java.nio.file.Files;
import java.nio.file.Path;
import java.nio.file.attribute.PosixFilePermissions;
import java.security.SecureRandom;
import java.time.Duration;
import java.time.Instant;
import java.util.ArrayList;
import java.util.Base64;
import java.util.Comparator;
import java.util.LinkedHashMap;
import java.util.List;
import java.util.Map;
import java.util.concurrent.TimeUnit;
import java.util.function.Predicate;
import java.util.stream.Stream;

/**
 * A CAST system for one test: {@code cast serve} on a free port of 127.0.0.1, with a secret made
 * for the test from which the kit mints every component's token, in a temporary directory of its
 * own. {@link #close()} stops every component it started and the server, and removes the
 * directory.
 *
 * <pre>
 * try (LocalSystem system = LocalSystem.start("vision")) {
 *   RunningComponent&lt;Counter&gt; counter = system.run(new Counter(), "counter", "vision", Args.fromJson("{\"to\": 3}"));
 *   system.actAs("camera", "vision").add("go", text("now"));
 *   system.waitForEntry("vision", "count", Int64Value.class, number(3));
 *   assertEquals(0, counter.stop());
 * }
 * </pre>
 *
 * <p>The {@code cast} command is found in {@code $CAST_SERVE}, else on PATH, else in the Python
 * package of python3 ({@code python3 -m cast.cli}); without one, {@link #start} throws
 * NotFoundError saying what to install. The names are those of the Python ({@code cast.testing})
 * and C++ ({@code cast/testing.h}) kits: docs/java.md, "Testing your components".
 */
public final class LocalSystem implements AutoCloseable {
  /** The id under which the kit itself reads (assertEntry): privileged, in the first SA. */
  static final String OBSERVER = "cast-testing";

  private final Path directory;
  private final byte[] secret;
  private final ServeProcess server;
  private final String name;
  private final List<String> subarchitectures;
  private final List<RunningComponent<?>> running = new ArrayList<>();
  private final List<ChangeCollector> collectors = new ArrayList<>();
  private final List<Component> components = new ArrayList<>();
  private Actor observer;
  private boolean closed;
  private int exitCode;
  private String output = "";

  private LocalSystem(Path directory, byte[] secret, ServeProcess server) {
    this.directory = directory;
    this.secret = secret;
    this.server = server;
    // The name and SAs as the server has them (the configuration is YAML, which only the server reads).
    SystemDescription description;
    ManagedChannel channel = channel();
    try {
      description = DirectoryGrpc.newBlockingStub(channel)
          .withInterceptors(MetadataUtils.newAttachHeadersInterceptor(bearer(token(OBSERVER, ""))))
          .withDeadlineAfter(30, TimeUnit.SECONDS)
          .describeSystem(DescribeSystemRequest.getDefaultInstance());
    } catch (StatusRuntimeException e) {
      throw new UnavailableError("the test's server did not describe its system (" + e.getStatus() + "); it printed:\n"
          + server.output());
    } finally {
      channel.shutdownNow();
    }
    this.name = description.getName();
    this.subarchitectures =
        description.getSubarchitecturesList().stream().map(SubarchitectureInfo::getName).toList();
  }

  /** A system of these SAs (default: vision and language), whose task managers adopt every task. */
  public static LocalSystem start(String... subarchitectures) {
    return start(new SystemOptions().subarchitectures(subarchitectures));
  }

  /** A system as {@code options} say: some SAs, or a configuration's YAML file. */
  public static LocalSystem start(SystemOptions options) {
    if (options.config() != null && !options.subarchitectures().isEmpty()) {
      throw new InvalidArgumentError("give SystemOptions a configuration or subarchitectures, not both: the "
          + "configuration names its own subarchitectures");
    }
    Path config = null;
    if (options.config() != null) {
      config = options.config().toAbsolutePath();
      if (!Files.isRegularFile(config)) {
        throw new NotFoundError("no configuration file " + config + ": give the path of a system's YAML file");
      }
    }
    List<String> command = ServeProcess.findCast(); // before anything is made: nothing to clean up
    Path directory;
    try {
      directory = Files.createTempDirectory("cast-testing-");
    } catch (IOException e) {
      throw new UncheckedIOException("cannot make a temporary directory for the test's system", e);
    }
    try {
      if (config == null) {
        List<String> sas = options.subarchitectures().isEmpty() ? List.of("vision", "language")
            : options.subarchitectures();
        StringBuilder yaml = new StringBuilder("system: test\nsubarchitectures:\n");
        for (String sa : sas) {
          yaml.append("  \"").append(sa.replace("\\", "\\\\").replace("\"", "\\\"")).append("\": {}\n");
        }
        config = directory.resolve("system.yaml");
        Files.writeString(config, yaml.toString());
      }
      byte[] raw = new byte[32];
      new SecureRandom().nextBytes(raw);
      byte[] secret = Base64.getUrlEncoder().withoutPadding().encodeToString(raw).getBytes(StandardCharsets.US_ASCII);
      Path secretFile = directory.resolve("secret");
      Files.write(secretFile, secret);
      Files.setPosixFilePermissions(secretFile, PosixFilePermissions.fromString("rw-------"));
      List<String> args = new ArrayList<>(List.of(config.toString(), "--secret-file", secretFile.toString()));
      options.sets().forEach((name, value) -> args.addAll(List.of("--set", name + "=" + value)));
      ServeProcess server = new ServeProcess(command, directory, args, options.startTimeout());
      try {
        return new LocalSystem(directory, secret, server);
      } catch (RuntimeException e) {
        server.stop();
        throw e;
      }
    } catch (IOException | RuntimeException e) {
      removeAll(directory);
      if (e instanceof IOException io) {
        throw new UncheckedIOException("cannot write the test system's files in " + directory, io);
      }
      throw (RuntimeException) e;
    }
  }

  // ------------------------------------------------------------------ who is who

  /** The directory's host:port (on 127.0.0.1). */
  public String endpoint() {
    return server.endpoint();
  }

  /** The system's name ({@code system:} of its configuration). */
  public String name() {
    return name;
  }

  /** Its SAs, in the configuration's order. */
  public List<String> subarchitectures() {
    return subarchitectures;
  }

  /** The system's temporary directory (configuration, secret, server log), removed by close(). */
  public Path directory() {
    return directory;
  }

  /** A token for a component of this system (what {@code cast token} would issue). */
  public String token(String componentId, String subarchitecture) {
    return token(componentId, subarchitecture, false);
  }

  /** A token for a component of this system, privileged or not. */
  public String token(String componentId, String subarchitecture, boolean privileged) {
    return Tokens.mint(secret, new Identity(componentId, subarchitecture, privileged), Instant.now().getEpochSecond());
  }

  /** {@link #launchEnvironment(String, String, Args, boolean)} without arguments, not privileged. */
  public Map<String, String> launchEnvironment(String componentId, String subarchitecture) {
    return launchEnvironment(componentId, subarchitecture, Args.empty(), false);
  }

  /**
   * The launch contract of a component process the test starts: CAST_ENDPOINT,
   * CAST_COMPONENT_ID, CAST_SUBARCHITECTURE, CAST_TOKEN and CAST_ARGS (put them into a
   * ProcessBuilder's environment).
   */
  public Map<String, String> launchEnvironment(
      String componentId, String subarchitecture, Args args, boolean privileged) {
    Map<String, String> env = new LinkedHashMap<>();
    env.put("CAST_ENDPOINT", endpoint());
    env.put("CAST_COMPONENT_ID", componentId);
    env.put("CAST_SUBARCHITECTURE", subarchitecture);
    env.put("CAST_TOKEN", token(componentId, subarchitecture, privileged));
    try {
      env.put("CAST_ARGS", com.google.protobuf.util.JsonFormat.printer().omittingInsignificantWhitespace()
          .print(args.toStruct()));
    } catch (com.google.protobuf.InvalidProtocolBufferException e) {
      throw new InvalidArgumentError("the component's arguments cannot be written as JSON: " + e.getMessage());
    }
    return env;
  }

  private LaunchContract contract(String componentId, String subarchitecture, boolean privileged, Args args) {
    checkOpen();
    if (!subarchitectures.contains(subarchitecture)) {
      throw new InvalidArgumentError("no subarchitecture '" + subarchitecture + "' in system '" + name + "' (it has "
          + String.join(", ", subarchitectures) + ")");
    }
    return new LaunchContract(endpoint(), componentId, subarchitecture,
        token(componentId, subarchitecture, privileged), args);
  }

  // ------------------------------------------------------------------ components

  /** The test acting as component {@code componentId} of {@code subarchitecture}. */
  public Actor actAs(String componentId, String subarchitecture) {
    return actAs(componentId, subarchitecture, false);
  }

  /** The test acting as a component, privileged or not. Closed with the system. */
  public Actor actAs(String componentId, String subarchitecture, boolean privileged) {
    return bind(new Actor(), componentId, subarchitecture, privileged);
  }

  /** {@link #bind(Component, String, String, boolean)}, not privileged. */
  public <C extends Component> C bind(C component, String componentId, String subarchitecture) {
    return bind(component, componentId, subarchitecture, false);
  }

  /**
   * A component bound to the system, its hooks left to the test to call (stepping). Closed with
   * the system.
   */
  public <C extends Component> C bind(C component, String componentId, String subarchitecture, boolean privileged) {
    Runner.connect(component, contract(componentId, subarchitecture, privileged, Args.empty()));
    components.add(component);
    return component;
  }

  /** {@link #run(Component, String, String, Args, boolean, Duration)} without arguments. */
  public <C extends Component> RunningComponent<C> run(C component, String componentId, String subarchitecture) {
    return run(component, componentId, subarchitecture, Args.empty(), false, CastTesting.DEFAULT_TIMEOUT);
  }

  /** {@link #run(Component, String, String, Args, boolean, Duration)}, not privileged, 10 s to start. */
  public <C extends Component> RunningComponent<C> run(
      C component, String componentId, String subarchitecture, Args args) {
    return run(component, componentId, subarchitecture, args, false, CastTesting.DEFAULT_TIMEOUT);
  }

  /**
   * A component running its lifecycle (configure(args), start(), run()) on a thread; returns once
   * start() returned, so its watches are registered. Stopped with the system.
   */
  public <C extends Component> RunningComponent<C> run(
      C component, String componentId, String subarchitecture, Args args, boolean privileged, Duration timeout) {
    Runner.connect(component, contract(componentId, subarchitecture, privileged, Args.empty()));
    RunningComponent<C> handle = new RunningComponent<>(component, args);
    running.add(handle);
    handle.awaitStarted(timeout);
    return handle;
  }

  // ------------------------------------------------------------------ observing

  private Actor observer() {
    if (observer == null) {
      observer = actAs(OBSERVER, subarchitectures.get(0), true);
    }
    return observer;
  }

  /** Every change of every SA, with its entry ({@link #collectChanges(List, String)}). */
  public ChangeCollector collectChanges() {
    return collectChanges(List.of(), "");
  }

  /** The changes matching {@code filters} ({@link #collectChanges(List, String)}). */
  public ChangeCollector collectChanges(ChangeFilter... filters) {
    return collectChanges(List.of(filters), "");
  }

  /**
   * Collects every change matching {@code filters} (none: every change of every SA, with its
   * entry); local filters mean {@code subarchitecture} (empty: the first SA). The watch is
   * registered before this returns.
   */
  public ChangeCollector collectChanges(List<ChangeFilter> filters, String subarchitecture) {
    String sa = subarchitecture.isEmpty() ? subarchitectures.get(0) : subarchitecture;
    LaunchContract contract = contract(OBSERVER + "-changes-" + (collectors.size() + 1), sa, true, Args.empty());
    Connection watcher = Cast.connect(new ConnectOptions().endpoint(contract.endpoint()).token(contract.token()));
    ChangeCollector collector = new ChangeCollector();
    collector.watchWith(watcher);
    collectors.add(collector);
    watcher.onChange(filters.isEmpty() ? List.of(Filters.operationFilter().withEntry()) : filters, collector::collect);
    return collector;
  }

  /** The entry, which must exist and be a {@code cls}; AssertionError saying what is there otherwise. */
  public <T extends Message> Entry<T> assertEntry(String subarchitecture, String id, Class<T> cls) {
    return assertEntry(subarchitecture, id, cls, (Predicate<T>) null);
  }

  /**
   * The entry, which must hold {@code expected} (equal field by field); AssertionError saying what it
   * holds otherwise. ({@code expected} is a Message, not a T, so that a lambda picks the overload
   * that takes a test.)
   */
  public <T extends Message> Entry<T> assertEntry(String subarchitecture, String id, Class<T> cls, Message expected) {
    Entry<T> entry = read(subarchitecture, id, cls);
    if (!entry.value().equals(expected)) {
      throw new AssertionError(where(subarchitecture, id) + " holds " + describe(entry) + ", expected "
          + CastTesting.describeValue(expected));
    }
    return entry;
  }

  /** The entry, whose value must pass {@code test}; AssertionError saying what it holds otherwise. */
  public <T extends Message> Entry<T> assertEntry(String subarchitecture, String id, Class<T> cls, Predicate<T> test) {
    Entry<T> entry = read(subarchitecture, id, cls);
    if (test != null && !test.test(entry.value())) {
      throw new AssertionError(where(subarchitecture, id) + " holds " + describe(entry) + ", which the test refused");
    }
    return entry;
  }

  /** Waits (10 s) until the entry holds {@code expected}; the failure says what it last held. */
  public <T extends Message> Entry<T> waitForEntry(String subarchitecture, String id, Class<T> cls, Message expected) {
    return waitForEntry(subarchitecture, id, cls, expected, CastTesting.DEFAULT_TIMEOUT);
  }

  /** Waits until the entry holds {@code expected}; the failure says what it last held. */
  public <T extends Message> Entry<T> waitForEntry(
      String subarchitecture, String id, Class<T> cls, Message expected, Duration timeout) {
    List<Entry<T>> found = new ArrayList<>(1);
    CastTesting.waitFor(() -> found.add(assertEntry(subarchitecture, id, cls, expected)), timeout,
        where(subarchitecture, id));
    return found.get(0);
  }

  /** Waits until the entry's value passes {@code test}; the failure says what it last held. */
  public <T extends Message> Entry<T> waitForEntry(
      String subarchitecture, String id, Class<T> cls, Predicate<T> test, Duration timeout) {
    List<Entry<T>> found = new ArrayList<>(1);
    CastTesting.waitFor(() -> found.add(assertEntry(subarchitecture, id, cls, test)), timeout,
        where(subarchitecture, id));
    return found.get(0);
  }

  private <T extends Message> Entry<T> read(String subarchitecture, String id, Class<T> cls) {
    try {
      return observer().getEntry(id, cls, subarchitecture);
    } catch (NotFoundError e) {
      throw new AssertionError("no " + where(subarchitecture, id) + "; " + listEntries(subarchitecture));
    } catch (InvalidArgumentError e) {
      throw new AssertionError(where(subarchitecture, id) + ": " + e.getMessage());
    }
  }

  private static String where(String subarchitecture, String id) {
    return "entry '" + id + "' in subarchitecture '" + subarchitecture + "'";
  }

  private static String describe(Entry<? extends Message> entry) {
    return CastTesting.describeValue(entry.value()) + " (version " + entry.version() + ", by " + entry.author() + ")";
  }

  /** The ids and types in an SA's WM, for a failure message (the listing `cast ls` shows). */
  private String listEntries(String subarchitecture) {
    ManagedChannel channel = channel();
    try {
      ListEntriesResponse listing = InspectionGrpc.newBlockingStub(channel)
          .withInterceptors(MetadataUtils.newAttachHeadersInterceptor(bearer(token(OBSERVER, subarchitecture))))
          .withDeadlineAfter(10, TimeUnit.SECONDS)
          .listEntries(ListEntriesRequest.newBuilder().setSubarchitecture(subarchitecture).build());
      if (listing.getEntriesCount() == 0) {
        return "that WM is empty";
      }
      List<String> ids = listing.getEntriesList().stream().limit(20)
          .map(e -> e.getAddress().getId() + " (" + e.getType() + ")").toList();
      return "entries there: " + String.join(", ", ids) + (listing.getEntriesCount() > 20 ? ", ..." : "");
    } catch (StatusRuntimeException e) {
      return "its entries could not be listed (" + e.getStatus().getCode() + ")";
    } finally {
      channel.shutdownNow();
    }
  }

  private ManagedChannel channel() {
    return ManagedChannelBuilder.forTarget(endpoint()).usePlaintext().build();
  }

  private static Metadata bearer(String token) {
    Metadata metadata = new Metadata();
    metadata.put(Metadata.Key.of("authorization", Metadata.ASCII_STRING_MARSHALLER), "Bearer " + token);
    return metadata;
  }

  // ------------------------------------------------------------------ the server

  /** What the server printed so far (after close(), all it printed): for failure messages. */
  public String output() {
    return closed ? output : server.output();
  }

  /** SIGKILL: the server is gone at once, as after a crash; clients see their connections break. */
  public void kill() {
    checkOpen();
    server.kill();
  }

  /** A new server with empty memories on the same address (the old one is killed first). */
  public void restart() {
    checkOpen();
    server.restart();
  }

  /** The server's exit status once closed (0 after a clean stop). */
  public int exitCode() {
    return exitCode;
  }

  private void checkOpen() {
    if (closed) {
      throw new InvalidArgumentError("system '" + name + "' is closed: start another one");
    }
  }

  /**
   * Stops everything: running components (stop() once each), collectors, bound components, the
   * server; removes the directory. Idempotent.
   */
  @Override
  public void close() {
    if (closed) {
      return;
    }
    closed = true;
    try {
      for (int i = running.size() - 1; i >= 0; i--) {
        try {
          running.get(i).stop();
        } catch (AssertionError e) {
          // one that does not stop is the test's to see in its exit code and log
        }
      }
      collectors.forEach(ChangeCollector::close);
      for (int i = components.size() - 1; i >= 0; i--) {
        components.get(i).close();
      }
    } finally {
      exitCode = server.stop();
      output = server.output(); // the log goes with the directory
      removeAll(directory);
    }
  }

  private static void removeAll(Path directory) {
    try (Stream<Path> files = Files.walk(directory)) {
      for (Path p : files.sorted(Comparator.reverseOrder()).toList()) {
        Files.deleteIfExists(p);
      }
    } catch (IOException e) {
      // a leftover temporary file is not the test's failure
    }
  }
}
