package cast.testing;

import cast.client.NotFoundError;
import cast.client.UnavailableError;
import java.io.File;
import java.io.IOException;
import java.io.OutputStream;
import java.io.UncheckedIOException;
import java.nio.charset.StandardCharsets;
import java.nio.file.Files;
import java.nio.file.Path;
import java.util.ArrayList;
import java.util.List;
import java.util.concurrent.TimeUnit;

/**
 * {@code cast serve} as a process of the test: finding the command, starting it on a free port,
 * reading the address it listens on, stopping it. Its standard input is a pipe only this JVM
 * holds, and it runs with {@code --exit-with-stdin}: when the JVM ends, however it ends, the
 * server stops.
 */
final class ServeProcess {
  private static final String LISTENING = "listening on ";

  private final List<String> argv;
  private final Path directory;
  private final Path log;
  private final java.time.Duration startTimeout;
  private Process process;
  private OutputStream lifeline;
  private String endpoint;

  ServeProcess(List<String> command, Path directory, List<String> serveArgs, java.time.Duration startTimeout) {
    this.argv = new ArrayList<>(command);
    argv.add("serve");
    argv.addAll(serveArgs);
    argv.add("--exit-with-stdin");
    this.directory = directory;
    this.log = directory.resolve("server.log");
    this.startTimeout = startTimeout;
    start("127.0.0.1:0");
  }

  /**
   * The command that runs {@code cast}: {@code $CAST_SERVE}, else {@code cast} on PATH, else
   * {@code python3 -m cast.cli} when python3 has the package; NotFoundError saying what to
   * install when there is none.
   */
  static List<String> findCast() {
    String given = System.getenv("CAST_SERVE");
    if (given != null && !given.isEmpty()) {
      if (!Files.isRegularFile(Path.of(given)) || !Files.isExecutable(Path.of(given))) {
        throw new NotFoundError(
            "CAST_SERVE names " + given + ", which is not an executable file: set it to the `cast` command of the "
                + "installed Python package cast-grpc (pip install cast-grpc), or unset it to use `cast` on PATH");
      }
      return List.of(given);
    }
    Path cast = onPath("cast");
    if (cast != null) {
      return List.of(cast.toString());
    }
    Path python = onPath("python3");
    if (python != null && succeeds(List.of(python.toString(), "-c", "import cast.cli"))) {
      return List.of(python.toString(), "-m", "cast.cli");
    }
    throw new NotFoundError(
        "cast-testing runs the CAST server, `cast serve`, and found none: not in CAST_SERVE, not `cast` on PATH, not "
            + "the Python package in python3; install it with `pip install cast-grpc` (docs/packages.md) into an "
            + "environment whose bin/ is on PATH, or set CAST_SERVE to its `cast` executable");
  }

  private static Path onPath(String name) {
    String path = System.getenv("PATH");
    if (path == null) {
      return null;
    }
    for (String dir : path.split(File.pathSeparator)) {
      Path candidate = Path.of(dir.isEmpty() ? "." : dir, name);
      if (Files.isRegularFile(candidate) && Files.isExecutable(candidate)) {
        return candidate;
      }
    }
    return null;
  }

  private static boolean succeeds(List<String> command) {
    try {
      Process p = new ProcessBuilder(command).redirectErrorStream(true).redirectOutput(ProcessBuilder.Redirect.DISCARD)
          .start();
      return p.waitFor(60, TimeUnit.SECONDS) && p.exitValue() == 0;
    } catch (IOException e) {
      return false;
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
      return false;
    }
  }

  private void start(String listen) {
    List<String> command = new ArrayList<>(argv);
    command.add("--listen");
    command.add(listen);
    ProcessBuilder builder = new ProcessBuilder(command).directory(directory.toFile()).redirectErrorStream(true)
        .redirectOutput(ProcessBuilder.Redirect.appendTo(log.toFile()));
    // The server is not a component: no launch contract of this process's goes to it.
    builder.environment().keySet().removeIf(name -> name.startsWith("CAST_"));
    long from;
    try {
      from = Files.exists(log) ? Files.size(log) : 0; // after a restart only what the new server prints counts
      process = builder.start();
    } catch (IOException e) {
      throw new UnavailableError("cannot start `" + String.join(" ", command) + "`: " + e.getMessage());
    }
    lifeline = process.getOutputStream();
    long deadline = System.nanoTime() + startTimeout.toNanos();
    while (System.nanoTime() - deadline < 0) {
      String text = printedSince(from);
      int at = text.indexOf(LISTENING);
      int eol = at < 0 ? -1 : text.indexOf('\n', at);
      if (eol >= 0) {
        endpoint = text.substring(at + LISTENING.length(), eol).trim();
        return;
      }
      if (!process.isAlive()) {
        throw new UnavailableError(
            "`" + argv.get(0) + " serve` exited (status " + process.exitValue() + ") before it listened; it printed:\n"
                + text);
      }
      try {
        Thread.sleep(20);
      } catch (InterruptedException e) {
        Thread.currentThread().interrupt();
        kill();
        throw new UnavailableError("interrupted while `cast serve` started");
      }
    }
    kill();
    throw new UnavailableError("`" + argv.get(0) + " serve` did not say it listens within " + startTimeout.toSeconds()
        + " s; it printed:\n" + output());
  }

  private String printedSince(long from) {
    String all = output();
    byte[] bytes = all.getBytes(StandardCharsets.UTF_8);
    return from >= bytes.length ? "" : new String(bytes, (int) from, bytes.length - (int) from, StandardCharsets.UTF_8);
  }

  String endpoint() {
    return endpoint;
  }

  /** What the servers started so far printed. */
  String output() {
    try {
      return Files.exists(log) ? Files.readString(log, StandardCharsets.UTF_8) : "";
    } catch (IOException e) {
      throw new UncheckedIOException(e);
    }
  }

  /** SIGTERM (the clean shutdown), SIGKILL after 30 s; the exit status. */
  int stop() {
    return end(false);
  }

  /** SIGKILL: gone at once. */
  void kill() {
    end(true);
  }

  /** kill(), then a new server on the same address. */
  void restart() {
    kill();
    start(endpoint);
  }

  private int end(boolean force) {
    if (process == null) {
      return 0;
    }
    try {
      lifeline.close();
    } catch (IOException e) {
      // the server is gone already
    }
    if (force) {
      process.destroyForcibly();
    } else {
      process.destroy();
    }
    try {
      if (!process.waitFor(30, TimeUnit.SECONDS)) {
        process.destroyForcibly();
        process.waitFor(30, TimeUnit.SECONDS);
      }
    } catch (InterruptedException e) {
      Thread.currentThread().interrupt();
      process.destroyForcibly();
    }
    return process.isAlive() ? -1 : process.exitValue();
  }
}
