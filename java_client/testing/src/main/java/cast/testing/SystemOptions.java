package cast.testing;

import java.nio.file.Path;
import java.time.Duration;
import java.util.ArrayList;
import java.util.LinkedHashMap;
import java.util.List;
import java.util.Map;

/**
 * How {@link LocalSystem#start(SystemOptions)} starts its server: a system of some SAs (default
 * vision and language, task managers adopting every task), or a configuration's YAML file.
 *
 * <pre>LocalSystem.start(new SystemOptions().config(Path.of("system.yaml")).set("SA", "eyes"))</pre>
 */
public final class SystemOptions {
  private final List<String> subarchitectures = new ArrayList<>();
  private Path config;
  private final Map<String, String> sets = new LinkedHashMap<>();
  private Duration startTimeout = Duration.ofSeconds(90);

  /** A system of these SAs, whose task managers adopt every task. */
  public SystemOptions subarchitectures(String... names) {
    subarchitectures.addAll(List.of(names));
    return this;
  }

  /** A configuration's YAML file: its SAs, policies, limits and in-process components. */
  public SystemOptions config(Path file) {
    this.config = file;
    return this;
  }

  /** A value of one of the configuration's variables ({@code cast serve --set NAME=VALUE}). */
  public SystemOptions set(String name, String value) {
    sets.put(name, value);
    return this;
  }

  /** How long {@code cast serve} may take to say it listens (default 90 s). */
  public SystemOptions startTimeout(Duration timeout) {
    this.startTimeout = timeout;
    return this;
  }

  List<String> subarchitectures() {
    return subarchitectures;
  }

  Path config() {
    return config;
  }

  Map<String, String> sets() {
    return sets;
  }

  Duration startTimeout() {
    return startTimeout;
  }
}
