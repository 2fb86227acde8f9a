package cast.testing;

import java.nio.file.Path;
import java.util.Optional;
import org.junit.jupiter.api.extension.AfterEachCallback;
import org.junit.jupiter.api.extension.BeforeEachCallback;
import org.junit.jupiter.api.extension.ExtensionContext;
import org.junit.jupiter.api.extension.ParameterContext;
import org.junit.jupiter.api.extension.ParameterResolver;
import org.junit.jupiter.api.extension.TestWatcher;

/**
 * The JUnit 5 extension of the kit: a {@link LocalSystem} for each test, handed to the test as a
 * parameter, closed after it also when it fails; a failed test's output gets what the server
 * printed.
 *
 * <pre>
 * class CounterTest {
 *   &#64;RegisterExtension static final CastExtension cast = CastExtension.withSubarchitectures("vision");
 *
 *   &#64;Test
 *   void countsToThree(LocalSystem system) { ... }
 * }
 * </pre>
 *
 * <p>{@code @ExtendWith(CastExtension.class)} gives a system of vision and language.
 */
public final class CastExtension implements BeforeEachCallback, AfterEachCallback, ParameterResolver, TestWatcher {
  private static final ExtensionContext.Namespace NAMESPACE = ExtensionContext.Namespace.create(CastExtension.class);
  private static final String SYSTEM = "system";
  private static final String OUTPUT = "output";

  private final SystemOptions options;

  /** A system of vision and language for each test. */
  public CastExtension() {
    this(new SystemOptions());
  }

  private CastExtension(SystemOptions options) {
    this.options = options;
  }

  /** A system of these SAs for each test. */
  public static CastExtension withSubarchitectures(String... names) {
    return new CastExtension(new SystemOptions().subarchitectures(names));
  }

  /** A system of this configuration for each test. */
  public static CastExtension withConfig(Path config) {
    return new CastExtension(new SystemOptions().config(config));
  }

  /** A system as {@code options} say for each test. */
  public static CastExtension withOptions(SystemOptions options) {
    return new CastExtension(options);
  }

  @Override
  public void beforeEach(ExtensionContext context) {
    context.getStore(NAMESPACE).put(SYSTEM, LocalSystem.start(options));
  }

  @Override
  public void afterEach(ExtensionContext context) {
    LocalSystem system = context.getStore(NAMESPACE).remove(SYSTEM, LocalSystem.class);
    if (system != null) {
      system.close();
      // What the server printed, for testFailed (which JUnit calls after this).
      context.getStore(NAMESPACE).put(OUTPUT, "cast system '" + system.name() + "' at " + system.endpoint()
          + " printed:\n" + system.output());
    }
  }

  @Override
  public void testFailed(ExtensionContext context, Throwable cause) {
    String output = context.getStore(NAMESPACE).remove(OUTPUT, String.class);
    if (output != null) {
      System.err.println(output);
    }
  }

  @Override
  public void testSuccessful(ExtensionContext context) {
    context.getStore(NAMESPACE).remove(OUTPUT);
  }

  @Override
  public void testAborted(ExtensionContext context, Throwable cause) {
    context.getStore(NAMESPACE).remove(OUTPUT);
  }

  @Override
  public void testDisabled(ExtensionContext context, Optional<String> reason) {}

  @Override
  public boolean supportsParameter(ParameterContext parameter, ExtensionContext context) {
    return parameter.getParameter().getType() == LocalSystem.class;
  }

  @Override
  public Object resolveParameter(ParameterContext parameter, ExtensionContext context) {
    return context.getStore(NAMESPACE).get(SYSTEM, LocalSystem.class);
  }
}
