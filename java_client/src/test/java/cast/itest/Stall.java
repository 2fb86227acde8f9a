package cast.itest;

import cast.client.AlreadyExistsError;
import cast.client.Cast;
import cast.client.CastError;
import cast.client.ConnectOptions;
import cast.client.Connection;
import cast.client.Filters;
import cast.client.LockMode;
import cast.testing.CastTesting.Counter;
import com.google.gson.JsonArray;
import com.google.gson.JsonObject;
import java.io.BufferedReader;
import java.io.InputStreamReader;
import java.nio.charset.StandardCharsets;
import java.time.Duration;
import java.util.ArrayList;
import java.util.LinkedHashMap;
import java.util.List;
import java.util.Map;

/**
 * Every kind of call at once against a server that stopped answering, for
 * tests/interop/test_hung_server.py: one connection per call ({@link Cast#connect}, tokens
 * minted from {@code $CAST_SECRET}), with the call timeout {@code $CAST_STALL_CALL_TIMEOUT_MS}
 * and the lock timeout {@code $CAST_STALL_LOCK_TIMEOUT_MS}. The same stdin/stdout protocol as
 * cpp_client/tests/components/cast_test_stall.cc, which describes it.
 *
 * <pre>java -cp ... cast.itest.Stall PREFIX</pre>
 */
public final class Stall {
  private static final List<String> KINDS =
      List.of(
          "add", "add_async", "overwrite", "delete", "batch", "lock", "try_lock", "unlock", "get", "get_all",
          "exists", "watch", "report");

  private Stall() {}

  private static synchronized void say(JsonObject line) {
    System.out.println(line);
    System.out.flush();
  }

  private static Duration envMillis(String name, long fallback) {
    String value = System.getenv(name);
    return Duration.ofMillis(value == null ? fallback : Long.parseLong(value));
  }

  private static Counter counter(long value) {
    return Counter.newBuilder().setWriter("java").setValue(value).build();
  }

  private static long msSince(long startNanos) {
    return (System.nanoTime() - startNanos) / 1_000_000;
  }

  /** Runs the protocol; exit 0 after "quit", 1 when the set-up fails. */
  public static void main(String[] argv) throws Exception {
    String p = argv[0];
    Duration callTimeout = envMillis("CAST_STALL_CALL_TIMEOUT_MS", 3000);
    Duration lockTimeout = envMillis("CAST_STALL_LOCK_TIMEOUT_MS", 4000);
    Map<String, Connection> conns = new LinkedHashMap<>();
    List<Long> seen = new ArrayList<>();
    Connection writer;
    Connection watcher;
    try {
      writer = open(p + "-writer", callTimeout);
      watcher = open(p + "-watcher", callTimeout);
      watcher.onChange(
          Filters.operationFilter().local(),
          change -> {
            synchronized (seen) {
              seen.add(change.revision());
              seen.notifyAll();
            }
          });
      for (String kind : KINDS) {
        conns.put(kind, open(p + "-" + kind, callTimeout));
      }
      // Every stream a call uses is open before the stall, as in a component that has been running.
      conns.get("add").add(p + "-warm-add", counter(0));
      conns.get("add_async").addAsync(p + "-warm-async", counter(0)).join();
      conns.get("overwrite").add(p + "-ow", counter(0));
      conns.get("delete").add(p + "-del", counter(0));
      conns.get("batch").add(p + "-warm-batch", counter(0));
      conns.get("lock").add(p + "-lk", counter(0));
      conns.get("lock").lock(p + "-lk", LockMode.O).unlock();
      conns.get("try_lock").add(p + "-warm-try", counter(0));
      conns.get("unlock").add(p + "-ul", counter(0));
      conns.get("unlock").lock(p + "-ul", LockMode.O); // held: "unlock" releases it during the stall
      conns.get("get").exists(p + "-ow");
      conns.get("watch").onChange(Filters.addressFilter(p + "-ow"), c -> {}); // its watch stream is open
      conns.get("report").report("warm", 1);
    } catch (CastError e) {
      JsonObject out = new JsonObject();
      out.addProperty("error", e.getClass().getSimpleName());
      out.addProperty("message", e.getMessage());
      say(out);
      System.exit(1);
      return;
    }
    JsonObject ready = new JsonObject();
    ready.addProperty("ready", true);
    say(ready);

    Map<String, Runnable> calls = new LinkedHashMap<>();
    calls.put("add", () -> conns.get("add").add(p + "-stalled-add", counter(1)));
    calls.put("add_async", () -> awaited(conns.get("add_async").addAsync(p + "-stalled-async", counter(1))));
    calls.put("overwrite", () -> conns.get("overwrite").overwrite(p + "-ow", counter(1)));
    calls.put("delete", () -> conns.get("delete").deleteEntry(p + "-del"));
    calls.put("batch", () -> conns.get("batch").batch().add(p + "-stalled-batch", counter(2)).apply());
    calls.put("lock", () -> conns.get("lock").lock(p + "-lk", LockMode.O, lockTimeout));
    calls.put("try_lock", () -> conns.get("try_lock").tryLock(p + "-lk", LockMode.O));
    calls.put("unlock", () -> conns.get("unlock").unlock(p + "-ul"));
    calls.put("get", () -> conns.get("get").get(p + "-ow", Counter.class));
    calls.put("get_all", () -> conns.get("get_all").getAll(Counter.class));
    calls.put("exists", () -> conns.get("exists").exists(p + "-ow"));
    calls.put("watch", () -> conns.get("watch").onChange(Filters.operationFilter().local(), c -> {}));
    calls.put("report", () -> conns.get("report").report("stalled", 1));

    int acked = 0;
    BufferedReader in = new BufferedReader(new InputStreamReader(System.in, StandardCharsets.UTF_8));
    String line;
    while ((line = in.readLine()) != null) {
      String[] words = line.trim().split("\\s+");
      switch (words[0]) {
        case "acked" -> {
          JsonArray ids = new JsonArray();
          for (int i = 0; i < Integer.parseInt(words[1]); i++) {
            String id = p + "-acked-" + acked++;
            writer.add(id, counter(i));
            ids.add(id);
          }
          JsonObject out = new JsonObject();
          out.add("acked", ids);
          say(out);
        }
        case "stall" -> {
          long start = System.nanoTime();
          List<Thread> threads = new ArrayList<>();
          for (var call : calls.entrySet()) {
            threads.add(
                started(
                        () -> {
                          JsonObject out = new JsonObject();
                          out.addProperty("call", call.getKey());
                          try {
                            call.getValue().run();
                            out.addProperty("ms", msSince(start));
                            out.add("error", null);
                          } catch (CastError e) {
                            out.addProperty("ms", msSince(start));
                            out.addProperty("error", e.getClass().getSimpleName());
                            out.addProperty("message", e.getMessage());
                          }
                          say(out);
                        }));
          }
          for (Thread t : threads) {
            t.join();
          }
          JsonObject out = new JsonObject();
          out.addProperty("stalled", true);
          say(out);
        }
        case "recover" -> {
          List<Thread> threads = new ArrayList<>();
          for (String kind : KINDS) {
            threads.add(started(() -> say(recover(conns.get(kind), kind, p))));
          }
          for (Thread t : threads) {
            t.join();
          }
          JsonObject out = new JsonObject();
          out.addProperty("recovered_all", true);
          say(out);
        }
        case "expect" -> {
          long revision = Long.parseLong(words[1]);
          long end = System.nanoTime() + Duration.ofSeconds(30).toNanos();
          JsonArray revisions = new JsonArray();
          synchronized (seen) {
            while (seen.stream().noneMatch(r -> r >= revision) && System.nanoTime() < end) {
              seen.wait(Math.max(1, (end - System.nanoTime()) / 1_000_000));
            }
            seen.forEach(revisions::add);
          }
          JsonObject out = new JsonObject();
          out.add("revisions", revisions);
          say(out);
        }
        case "quit" -> {
          for (Connection c : conns.values()) {
            c.close();
          }
          watcher.close();
          writer.close();
          System.exit(0);
        }
        default -> throw new IllegalArgumentException("unknown command: " + line);
      }
    }
  }

  /** The future's result; its failure thrown as the named error it carries. */
  private static void awaited(java.util.concurrent.CompletableFuture<?> future) {
    try {
      future.join();
    } catch (java.util.concurrent.CompletionException e) {
      if (e.getCause() instanceof CastError error) {
        throw error;
      }
      throw e;
    }
  }

  private static Thread started(Runnable body) {
    Thread thread = new Thread(body);
    thread.start();
    return thread;
  }

  private static Connection open(String componentId, Duration callTimeout) {
    return Cast.connect(
        new ConnectOptions().componentId(componentId).subarchitecture("vision").callTimeout(callTimeout));
  }

  /** Writes on {@code conn} until a write succeeds (60 s at most); how long it took and how many tries. */
  private static JsonObject recover(Connection conn, String kind, String p) {
    long start = System.nanoTime();
    int tries = 0;
    String last = null;
    while (msSince(start) < 60_000) {
      tries++;
      try {
        conn.add(p + "-recovered-" + kind, counter(3));
        last = null;
        break;
      } catch (AlreadyExistsError e) {
        last = null; // an earlier try was applied after all
        break;
      } catch (CastError e) {
        last = e.getClass().getSimpleName() + ": " + e.getMessage();
        try {
          Thread.sleep(50);
        } catch (InterruptedException interrupted) {
          Thread.currentThread().interrupt();
          break;
        }
      }
    }
    JsonObject out = new JsonObject();
    out.addProperty("recovered", kind);
    out.addProperty("ms", msSince(start));
    out.addProperty("tries", tries);
    if (last != null) {
      out.addProperty("error", last);
    }
    return out;
  }
}
