package cast.itest;

import cast.client.Cast;
import cast.client.CastError;
import cast.client.ConnectOptions;
import cast.client.Connection;
import cast.client.Entry;
import cast.client.Filters;
import cast.client.Operation;
import cast.client.WatchHandle;
import cast.testing.CastTesting.Counter;
import com.google.gson.JsonObject;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.TimeUnit;
import java.util.concurrent.TimeoutException;

/**
 * A plain program (no component, no runner) that uses a working memory through
 * {@link Cast#connect()}, for tests/interop/test_connect.py. It finds the system as any
 * script would (environment, runtime directory), watches the entry ID, adds it, reads
 * it back, waits for its change, and prints one JSON line
 * {"component", "subarchitecture", "privileged", "version", "event", "writer"}. Exit 0
 * on success; 1 with {"error": name, "message": ...} on a CastError. CONNECT_OPTION_COMPONENT_ID
 * and CONNECT_OPTION_SUBARCHITECTURE, when set, are given as ConnectOptions (tests of options
 * that contradict the token, tests/interop/test_java_identity.py).
 *
 * <pre>java -cp cast-client-all.jar:test-classes cast.itest.ConnectScript ID</pre>
 */
public final class ConnectScript {
  private ConnectScript() {}

  /** The program. */
  public static void main(String[] argv) throws Exception {
    if (argv.length != 1) {
      System.err.println("usage: cast.itest.ConnectScript ENTRY_ID");
      System.exit(2);
    }
    String id = argv[0];
    JsonObject out = new JsonObject();
    int status = 0;
    ConnectOptions options = new ConnectOptions();
    if (System.getenv("CONNECT_OPTION_COMPONENT_ID") != null) {
      options.componentId(System.getenv("CONNECT_OPTION_COMPONENT_ID"));
    }
    if (System.getenv("CONNECT_OPTION_SUBARCHITECTURE") != null) {
      options.subarchitecture(System.getenv("CONNECT_OPTION_SUBARCHITECTURE"));
    }
    try (Connection wm = Cast.connect(options)) {
      CompletableFuture<String> changed = new CompletableFuture<>();
      WatchHandle watch =
          wm.onChange(Filters.addressFilter(id, Operation.ADD), change -> changed.complete(change.operation().name()));
      wm.add(id, Counter.newBuilder().setWriter(wm.componentId()).setValue(42).build());
      Entry<Counter> entry = wm.getEntry(id, Counter.class);
      String event = changed.get(20, TimeUnit.SECONDS);
      watch.cancel();
      out.addProperty("component", wm.componentId());
      out.addProperty("subarchitecture", wm.subarchitecture());
      out.addProperty("privileged", wm.isPrivileged());
      out.addProperty("version", entry.version());
      out.addProperty("event", event);
      out.addProperty("writer", entry.value().getWriter());
    } catch (CastError e) {
      out.addProperty("error", e.getClass().getSimpleName());
      out.addProperty("message", e.getMessage());
      status = 1;
    } catch (TimeoutException e) {
      out.addProperty("error", "Timeout");
      out.addProperty("message", "no change event within 20 s");
      status = 1;
    }
    System.out.println(out);
    System.exit(status);
  }
}
