package cast.client;

import java.lang.reflect.Constructor;
import java.lang.reflect.InvocationTargetException;
import java.lang.reflect.Modifier;
import java.lang.reflect.Proxy;
import java.time.Duration;
import java.util.Map;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.atomic.AtomicBoolean;
import java.util.function.Function;
import java.util.logging.Level;
import java.util.logging.Logger;

/**
 * Runs one component process from the launch contract (docs/design.md section 6):
 *
 * <pre>java -cp cast-client-all.jar:&lt;component classes&gt; cast.client.Runner com.example.MyComponent</pre>
 *
 * <p>Reads CAST_ENDPOINT, CAST_COMPONENT_ID, CAST_SUBARCHITECTURE, CAST_TOKEN_FILE or
 * CAST_TOKEN ({@link LaunchContract}) and CAST_ARGS; connects; calls configure(args), start(), run() (with CAST_START_BARRIER=1,
 * as {@code cast run} launches it, run() waits until every component of the system has
 * finished start(): a watch made in start() misses nothing written in run()); calls stop() once on
 * SIGTERM/SIGINT, on {@code requestStop()}, or when a hook failed. Exit status: 0
 * after a clean stop, 1 when a hook failed, 2 for a bad command line or launch
 * environment (or a system that refuses the token, or does not answer within the
 * connect window: {@link ConnectWindow}).
 */
public final class Runner {
  private static final Logger LOG = Logger.getLogger("cast.run");
  static final String USAGE =
      "usage: java -cp cast-client-all.jar:<classes> cast.client.Runner <fully.qualified.ComponentClass>\n"
          + "  (reads CAST_ENDPOINT, CAST_COMPONENT_ID, CAST_SUBARCHITECTURE, CAST_TOKEN_FILE or CAST_TOKEN,\n"
          + "   CAST_ARGS from the environment)";

  private Runner() {}

  /** The process entry point. */
  public static void main(String[] argv) {
    configureLogging(System.getenv("CAST_LOG_LEVEL"));
    System.exit(run(argv, System.getenv(), true));
  }

  /** Run a component from a command line and an environment; returns the exit status. */
  static int run(String[] argv, Map<String, String> env, boolean handleSignals) {
    return run(argv, env, handleSignals, GrpcTransport::new);
  }

  /** The same, connecting through {@code transports} (tests give an in-memory one). */
  static int run(
      String[] argv, Map<String, String> env, boolean handleSignals, Function<LaunchContract, Transport> transports) {
    return run(argv, env, handleSignals, transports, null);
  }

  /**
   * The same, asking a server that does not answer again within {@code window} (tests give a short
   * one; null: {@code CAST_CONNECT_WINDOW_S} from {@code env}, else 20 s).
   */
  static int run(
      String[] argv,
      Map<String, String> env,
      boolean handleSignals,
      Function<LaunchContract, Transport> transports,
      ConnectWindow window) {
    if (argv.length != 1 || argv[0].equals("-h") || argv[0].equals("--help")) {
      System.err.println(USAGE);
      return 2;
    }
    Component component;
    LaunchContract contract;
    ConnectWindow asking;
    try {
      Class<? extends Component> cls = loadComponentClass(argv[0]);
      contract = LaunchContract.fromEnv(env);
      asking = window != null ? window : ConnectWindow.fromEnv(env);
      component = instantiate(cls);
    } catch (InvalidArgumentError e) {
      System.err.println("cast.client.Runner: " + e.getMessage());
      return 2;
    } catch (RuntimeException e) {
      LOG.log(Level.SEVERE, "constructing " + argv[0] + " failed", e);
      return 1;
    }
    try {
      // The system was started first: a server that does not answer yet is busy or starting.
      Transport transport =
          asking.connect(contract.endpoint(), contract.tls() != null, () -> transports.apply(contract));
      component.bind(transport, who -> verifyLaunchIdentity(contract, who));
    } catch (CastError e) {
      System.err.println(
          "cast.client.Runner: cannot join the system at " + contract.endpoint() + ": " + e.getMessage());
      return 2;
    } catch (IllegalArgumentException e) { // a CAST_ENDPOINT grpc cannot parse as host:port
      System.err.println("cast.client.Runner: bad CAST_ENDPOINT '" + contract.endpoint() + "': " + e.getMessage());
      return 2;
    }
    return runComponent(component, contract.args(), handleSignals, contract.startBarrier());
  }

  /** The component class named {@code className}; InvalidArgumentError saying what is wrong. */
  public static Class<? extends Component> loadComponentClass(String className) {
    Class<?> cls;
    try {
      ClassLoader loader = Thread.currentThread().getContextClassLoader();
      cls = Class.forName(className, true, loader == null ? Runner.class.getClassLoader() : loader);
    } catch (ClassNotFoundException | LinkageError e) {
      throw new InvalidArgumentError(
          "cannot load component class '"
              + className
              + "': "
              + (e instanceof ClassNotFoundException ? "not on the class path" : e.toString())
              + " (java -cp cast-client-all.jar:<your classes> cast.client.Runner "
              + className
              + ")");
    }
    if (!Component.class.isAssignableFrom(cls)) {
      throw new InvalidArgumentError(
          "'"
              + className
              + "' is not a component class: it must extend cast.client.UnmanagedComponent or"
              + " cast.client.ManagedComponent");
    }
    if (Modifier.isAbstract(cls.getModifiers())) {
      throw new InvalidArgumentError("component class '" + className + "' is abstract: the runner needs a concrete class");
    }
    @SuppressWarnings("unchecked")
    Class<? extends Component> c = (Class<? extends Component>) cls;
    return c;
  }

  private static Component instantiate(Class<? extends Component> cls) {
    Constructor<? extends Component> ctor;
    try {
      ctor = cls.getConstructor();
    } catch (NoSuchMethodException e) {
      throw new InvalidArgumentError(
          "component class '" + cls.getName() + "' needs a public no-argument constructor (and must be a public class)");
    }
    try {
      return ctor.newInstance();
    } catch (InvocationTargetException e) {
      Throwable cause = e.getCause();
      throw cause instanceof RuntimeException ? (RuntimeException) cause : new RuntimeException(cause);
    } catch (ReflectiveOperationException e) {
      throw new InvalidArgumentError("cannot construct component class '" + cls.getName() + "': " + e);
    }
  }

  /**
   * Connect a component to the system of {@code contract} without running it:
   * for tests and for programs that drive a component themselves. Close it with
   * {@link Component#close()}.
   */
  public static <C extends Component> C connect(C component, LaunchContract contract) {
    component.bind(new GrpcTransport(contract), who -> verifyLaunchIdentity(contract, who));
    return component;
  }

  /**
   * InvalidArgumentError naming both when CAST_COMPONENT_ID or CAST_SUBARCHITECTURE
   * is not the identity the server verified from CAST_TOKEN: a component must not act
   * under one name while the system knows it under another.
   */
  static void verifyLaunchIdentity(LaunchContract contract, Identity verified) {
    Session.requireVerified(
        verified,
        contract.componentId(),
        "CAST_COMPONENT_ID",
        contract.subarchitecture(),
        "CAST_SUBARCHITECTURE",
        "the launch environment and the token disagree; give the component a token for '"
            + contract.componentId()
            + "' in '"
            + contract.subarchitecture()
            + "' (`cast token "
            + contract.componentId()
            + " --sa "
            + contract.subarchitecture()
            + "`), or the launch environment of its token");
  }

  /** Drives one component through configure, start, run and stop. */
  private static final class Lifecycle {
    private final Component component;
    private final Args args;
    private final boolean startBarrier;
    private final AtomicBoolean stopCalled = new AtomicBoolean();
    private final AtomicBoolean saidStarted = new AtomicBoolean();
    private final Runnable onStarted;
    volatile boolean failed;

    Lifecycle(Component component, Args args, boolean startBarrier, Runnable onStarted) {
      this.component = component;
      this.args = args;
      this.startBarrier = startBarrier;
      this.onStarted = onStarted;
    }

    /** onStarted, once. */
    private void sayStarted() {
      if (onStarted != null && saidStarted.compareAndSet(false, true)) {
        onStarted.run();
      }
    }

    /** Call stop() exactly once. */
    void stop() {
      if (!stopCalled.compareAndSet(false, true)) {
        return;
      }
      component.setState(ComponentState.STOPPING);
      component.requestStop();
      try {
        component.stop();
      } catch (Throwable e) { // report, and still shut down
        LOG.log(Level.SEVERE, component.componentId() + ": stop() failed", e);
        failed = true;
      }
    }

    /** configure, start, run; stop() on failure. */
    void run() {
      try {
        component.configure(args);
        component.start();
        if (startBarrier) {
          // Watches made in start() are registered by now: say so, and run() only once every
          // component has, so none misses what another writes first thing in run().
          component.setState(ComponentState.STARTED);
          if (!component.transport().awaitRun(component::waitForStop)) {
            return; // asked to stop before the system got going: stop() follows, run() never ran
          }
        }
        component.setState(ComponentState.RUNNING);
        sayStarted();
        component.run();
      } catch (Throwable e) {
        LOG.log(Level.SEVERE, component.componentId() + " failed", e);
        failed = true;
        stop();
      } finally {
        sayStarted(); // also when the lifecycle ended before run(): nobody waits forever
      }
    }
  }

  /**
   * Run a connected component to the end and close it; returns the exit status
   * (0 ok, 1 failed). run() executes on a worker thread so that a signal can call
   * stop() while run() is busy; after run() returns the component keeps serving
   * callbacks until it is asked to stop.
   */
  public static int runComponent(Component component, Args args, boolean handleSignals) {
    return runComponent(component, args, handleSignals, false);
  }

  /**
   * The same; with {@code startBarrier} (a component `cast run` launched, CAST_START_BARRIER=1)
   * run() waits after start() until every component of the system has started.
   */
  public static int runComponent(Component component, Args args, boolean handleSignals, boolean startBarrier) {
    return runComponent(component, args, handleSignals, startBarrier, null);
  }

  /**
   * The same; {@code onStarted} (may be null) is called once, on the lifecycle's thread, when
   * run() is about to begin (start() returned: its watches are registered), or when the
   * lifecycle ended before that (a hook threw, or the component was stopped first): what
   * cast-testing waits for before it hands a running component to a test.
   */
  public static int runComponent(
      Component component, Args args, boolean handleSignals, boolean startBarrier, Runnable onStarted) {
    Lifecycle life = new Lifecycle(component, args, startBarrier, onStarted);
    CountDownLatch finished = new CountDownLatch(1);
    Thread hook = null;
    if (handleSignals) {
      installSignalHandlers(component::requestStop);
      // Safety net for a JVM shutdown we did not start (a signal the handlers do
      // not cover, System.exit from a component): stop cleanly before the JVM goes.
      hook =
          new Thread(
              () -> {
                component.requestStop();
                try {
                  finished.await(15, TimeUnit.SECONDS);
                } catch (InterruptedException e) {
                  Thread.currentThread().interrupt();
                }
              },
              "cast-shutdown");
      Runtime.getRuntime().addShutdownHook(hook);
    }
    Thread worker = new Thread(life::run, "cast-run-" + component.componentId());
    worker.setDaemon(true);
    worker.start();
    try {
      while (!component.waitForStop(Duration.ofMillis(200))) {
        if (!worker.isAlive() && life.failed) {
          break;
        }
      }
      life.stop();
      worker.join(10_000);
      if (worker.isAlive()) {
        LOG.severe(component.componentId() + ": run() did not return within 10 s of stop(); interrupting it");
        worker.interrupt();
        worker.join(1_000);
        life.failed = true;
      }
      component.drain(Duration.ofSeconds(5));
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
      life.failed = true;
    } finally {
      component.close();
      finished.countDown();
    }
    if (hook != null) {
      try {
        Runtime.getRuntime().removeShutdownHook(hook);
      } catch (IllegalStateException e) {
        // the JVM is already shutting down: the hook is running and sees `finished`
      }
    }
    return life.failed ? 1 : 0;
  }

  /**
   * Make SIGTERM and SIGINT call {@code onSignal} instead of exiting the JVM, so the
   * runner stops the component and exits with its own status. Uses sun.misc.Signal
   * (module jdk.unsupported, present in every OpenJDK) through reflection to avoid a
   * compile-time dependency; without it the shutdown hook still calls stop().
   */
  static boolean installSignalHandlers(Runnable onSignal) {
    try {
      Class<?> signalClass = Class.forName("sun.misc.Signal");
      Class<?> handlerClass = Class.forName("sun.misc.SignalHandler");
      Object handler =
          Proxy.newProxyInstance(
              Runner.class.getClassLoader(),
              new Class<?>[] {handlerClass},
              (proxy, method, args) -> {
                if (method.getName().equals("handle")) {
                  onSignal.run();
                  return null;
                }
                if (method.getName().equals("equals")) {
                  return proxy == args[0];
                }
                if (method.getName().equals("hashCode")) {
                  return System.identityHashCode(proxy);
                }
                return "cast-signal-handler";
              });
      for (String name : new String[] {"TERM", "INT"}) {
        Object signal = signalClass.getConstructor(String.class).newInstance(name);
        signalClass.getMethod("handle", signalClass, handlerClass).invoke(null, signal, handler);
      }
      return true;
    } catch (ReflectiveOperationException | RuntimeException e) {
      LOG.warning("cannot handle SIGTERM/SIGINT directly (" + e + "); relying on the shutdown hook");
      return false;
    }
  }

  /** One line per record on stderr, at CAST_LOG_LEVEL (DEBUG, INFO, WARNING, ERROR; default INFO). */
  static void configureLogging(String level) {
    if (System.getProperty("java.util.logging.SimpleFormatter.format") == null) {
      System.setProperty("java.util.logging.SimpleFormatter.format", "%1$tF %1$tT %3$s: %4$s: %5$s%6$s%n");
    }
    Level lvl;
    switch (level == null ? "INFO" : level.toUpperCase()) {
      case "DEBUG":
        lvl = Level.FINE;
        break;
      case "WARNING":
      case "WARN":
        lvl = Level.WARNING;
        break;
      case "ERROR":
      case "CRITICAL":
        lvl = Level.SEVERE;
        break;
      default:
        lvl = Level.INFO;
    }
    Logger root = Logger.getLogger("");
    root.setLevel(lvl);
    for (var h : root.getHandlers()) {
      h.setLevel(lvl);
    }
  }
}
