package cast.itest;

import cast.client.Args;
import cast.client.CastError;
import cast.client.ChangeFilter;
import cast.client.Entry;
import cast.client.Filters;
import cast.client.LockMode;
import cast.client.ManagedComponent;
import cast.client.Operation;
import cast.client.Task;
import cast.client.TaskOutcome;
import cast.client.WatchHandle;
import cast.client.WorkingMemoryChange;
import cast.client.WriteResult;
import cast.testing.CastTesting.Counter;
import cast.testing.CastTesting.Pose;
import cast.testing.RichEntry;
import com.google.gson.Gson;
import com.google.gson.JsonArray;
import com.google.gson.JsonElement;
import com.google.gson.JsonObject;
import com.google.gson.JsonParser;
import com.google.protobuf.Message;
import com.google.protobuf.util.JsonFormat;
import java.io.BufferedReader;
import java.io.InputStreamReader;
import java.io.PrintStream;
import java.nio.charset.StandardCharsets;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.Map;
import java.util.concurrent.ConcurrentHashMap;
import java.util.concurrent.LinkedBlockingQueue;
import java.util.concurrent.TimeUnit;

/**
 * A Java component driven line by line by a pytest interop test: each stdin line
 * is a JSON command ({"seq": n, "op": ..., ...}) that it carries out with the
 * component API, answering one JSON line {"reply": n, "ok": ...} on stdout.
 * Hooks print {"event": ...} lines; changes of a "watch" are recorded and read
 * back with "watch_stats". Logs go to stderr. Run by tests/interop/test_java_*.py
 * as `java -cp cast-client-all.jar:test-classes cast.client.Runner cast.itest.Driven`.
 */
public class Driven extends ManagedComponent {
  private static final Gson GSON = new Gson();
  private final PrintStream out = new PrintStream(System.out, true, StandardCharsets.UTF_8);
  private final LinkedBlockingQueue<String> commands = new LinkedBlockingQueue<>();
  private final Map<Integer, Recorded> watches = new ConcurrentHashMap<>();
  private final Map<String, Task> tasks = new ConcurrentHashMap<>();
  private final java.util.concurrent.CountDownLatch gate = new java.util.concurrent.CountDownLatch(1);
  private final java.util.concurrent.atomic.AtomicLong delivered = new java.util.concurrent.atomic.AtomicLong();

  /** DRIVEN_MAX_PENDING lets a test make the dispatcher queue small (a slow watcher lags sooner). */
  @Override
  protected int maxPendingCallbacks() {
    String n = System.getenv("DRIVEN_MAX_PENDING");
    return n == null ? super.maxPendingCallbacks() : Integer.parseInt(n);
  }

  /** The changes one watch received, in delivery order. */
  static final class Recorded {
    final WatchHandle handle;
    final List<JsonObject> events = new ArrayList<>(); // guarded by this
    final List<String> threads = new ArrayList<>(); // guarded by this

    Recorded(WatchHandle handle) {
      this.handle = handle;
    }
  }

  static Class<? extends Message> typeClass(String name) {
    switch (name) {
      case "cast.testing.Counter":
        return Counter.class;
      case "cast.testing.Pose":
        return Pose.class;
      case "cast.testing.RichEntry":
        return RichEntry.class;
      default:
        throw new IllegalArgumentException("Driven knows no type " + name);
    }
  }

  static Message parse(String type, JsonElement json) throws Exception {
    Message.Builder b = (Message.Builder) typeClass(type).getMethod("newBuilder").invoke(null);
    JsonFormat.parser().merge(GSON.toJson(json), b);
    return b.build();
  }

  static JsonElement print(Message m) throws Exception {
    return JsonParser.parseString(JsonFormat.printer().print(m));
  }

  synchronized void emit(JsonObject line) {
    out.println(GSON.toJson(line));
  }

  void event(String kind, JsonObject body) {
    body.addProperty("event", kind);
    emit(body);
  }

  @Override
  public void configure(Args args) {
    log().info("configured with " + args);
  }

  @Override
  public void start() {
    Thread reader =
        new Thread(
            () -> {
              try (BufferedReader in = new BufferedReader(new InputStreamReader(System.in, StandardCharsets.UTF_8))) {
                String line;
                while ((line = in.readLine()) != null) {
                  commands.add(line);
                }
              } catch (Exception e) {
                log().warning("stdin: " + e);
              }
              commands.add("EOF");
            },
            "driven-stdin");
    reader.setDaemon(true);
    reader.start();
    JsonObject ready = new JsonObject();
    ready.addProperty("component", componentId());
    ready.addProperty("subarchitecture", subarchitecture());
    ready.addProperty("privileged", isPrivileged());
    event("ready", ready);
  }

  @Override
  public void run() throws Exception {
    while (isRunning()) {
      String line = commands.poll(100, TimeUnit.MILLISECONDS);
      if (line == null) {
        continue;
      }
      if (line.equals("EOF")) {
        requestStop();
        return;
      }
      JsonObject cmd = JsonParser.parseString(line).getAsJsonObject();
      JsonObject reply = new JsonObject();
      reply.addProperty("reply", cmd.get("seq").getAsInt());
      try {
        execute(cmd, reply);
        reply.addProperty("ok", true);
      } catch (CastError e) {
        reply.addProperty("ok", false);
        reply.addProperty("error", e.getClass().getSimpleName());
        reply.addProperty("code", e.code());
        reply.addProperty("message", e.getMessage());
      }
      emit(reply);
    }
  }

  @Override
  public void stop() {
    event("stopping", new JsonObject());
  }

  private static String str(JsonObject o, String k) {
    return o.has(k) && !o.get(k).isJsonNull() ? o.get(k).getAsString() : null;
  }

  private static Long lng(JsonObject o, String k) {
    return o.has(k) && !o.get(k).isJsonNull() ? o.get(k).getAsLong() : null;
  }

  private static void result(JsonObject reply, WriteResult r) {
    reply.addProperty("revision", r.revision());
    reply.addProperty("version", r.version());
  }

  private static Operation[] ops(JsonObject f) {
    List<Operation> list = new ArrayList<>();
    if (f.has("operations")) {
      for (JsonElement e : f.getAsJsonArray("operations")) {
        list.add(Operation.valueOf(e.getAsString()));
      }
    }
    return list.toArray(new Operation[0]);
  }

  static ChangeFilter filter(JsonObject f) {
    ChangeFilter filter;
    switch (f.get("kind").getAsString()) {
      case "local_type":
        filter = Filters.localTypeFilter(typeClass(str(f, "type")), ops(f));
        break;
      case "global_type":
        filter = Filters.globalTypeFilter(typeClass(str(f, "type")), ops(f));
        break;
      case "address":
        filter = Filters.addressFilter(str(f, "id"), ops(f));
        break;
      case "source":
        filter = Filters.sourceFilter(str(f, "component"), ops(f));
        break;
      case "operation":
        filter = Filters.operationFilter(ops(f));
        break;
      default:
        throw new IllegalArgumentException("unknown filter kind " + f.get("kind"));
    }
    if (f.has("sa")) {
      filter = filter.inSubarchitecture(str(f, "sa"));
    }
    if (f.has("include_entry") && f.get("include_entry").getAsBoolean()) {
      filter = filter.withEntry();
    }
    return filter;
  }

  private void record(Recorded rec, WorkingMemoryChange ch) throws Exception {
    JsonObject e = new JsonObject();
    e.addProperty("op", ch.operation().name());
    e.addProperty("id", ch.id());
    e.addProperty("sa", ch.subarchitecture());
    e.addProperty("type", ch.type());
    e.addProperty("revision", ch.revision());
    e.addProperty("version", ch.version());
    e.addProperty("source", ch.sourceComponent());
    if (ch.hasEntry() && ch.operation() != Operation.DELETE && ch.type().equals("cast.testing.Counter")) {
      e.add("value", print(ch.entry(Counter.class).value()));
    }
    Streamed.describe(e, ch);
    e.addProperty("seq", delivered.incrementAndGet()); // the order callbacks ran in, across watches (priorities)
    synchronized (rec) {
      rec.events.add(e);
      if (!rec.threads.contains(Thread.currentThread().getName())) {
        rec.threads.add(Thread.currentThread().getName());
      }
      rec.notifyAll();
    }
  }

  private void execute(JsonObject c, JsonObject reply) throws Exception {
    String sa = str(c, "sa");
    switch (c.get("op").getAsString()) {
      case "whoami":
        reply.addProperty("component", componentId());
        reply.addProperty("subarchitecture", subarchitecture());
        reply.addProperty("privileged", isPrivileged());
        break;
      case "new_id":
        reply.addProperty("id", newId());
        break;
      case "add":
        result(reply, add(str(c, "id"), parse(str(c, "type"), c.get("value")), sa));
        break;
      case "overwrite":
        result(reply, overwrite(str(c, "id"), parse(str(c, "type"), c.get("value")), sa, lng(c, "expected_version")));
        break;
      case "delete":
        result(reply, deleteEntry(str(c, "id"), sa, lng(c, "expected_version")));
        break;
      case "get":
        {
          Entry<? extends Message> e = getEntry(str(c, "id"), typeClass(str(c, "type")), sa);
          reply.add("value", print(e.value()));
          reply.addProperty("version", e.version());
          reply.addProperty("author", e.author());
          reply.addProperty("type", e.type());
        }
        break;
      case "get_all":
        {
          JsonArray arr = new JsonArray();
          for (Entry<? extends Message> e : getAll(typeClass(str(c, "type")), sa)) {
            JsonObject o = new JsonObject();
            o.addProperty("id", e.id());
            o.add("value", print(e.value()));
            o.addProperty("version", e.version());
            arr.add(o);
          }
          reply.add("entries", arr);
        }
        break;
      case "exists":
        reply.addProperty("exists", exists(str(c, "id"), sa));
        break;
      case "lock":
        {
          Long ms = lng(c, "timeout_ms");
          reply.addProperty(
              "depth",
              lock(str(c, "id"), LockMode.valueOf(str(c, "mode")), sa, ms == null ? null : Duration.ofMillis(ms))
                  .depth());
        }
        break;
      case "try_lock":
        reply.addProperty("locked", tryLock(str(c, "id"), LockMode.valueOf(str(c, "mode")), sa));
        break;
      case "unlock":
        reply.addProperty("depth", unlock(str(c, "id"), sa));
        break;
      case "watch":
        {
          List<ChangeFilter> filters = new ArrayList<>();
          for (JsonElement f : c.getAsJsonArray("filters")) {
            filters.add(filter(f.getAsJsonObject()));
          }
          Recorded[] holder = new Recorded[1];
          boolean gated = c.has("gated") && c.get("gated").getAsBoolean();
          long slowMs = c.has("slow_ms") ? c.get("slow_ms").getAsLong() : 0;
          WatchHandle h =
              onChange(
                  filters,
                  ch -> {
                    if (gated) {
                      gate.await(); // a stuck callback, until "open_gate"
                    }
                    Thread.sleep(slowMs); // a consumer slower than the writer ("slow_ms")
                    record(holder[0], ch);
                  },
                  Streamed.options(c)); // "delivery", "priority"
          holder[0] = new Recorded(h);
          watches.put(h.watchId(), holder[0]);
          reply.addProperty("watch", h.watchId());
        }
        break;
      case "watch_stats":
        {
          Recorded rec = watches.get(c.get("watch").getAsInt());
          long expected = c.has("expected") ? c.get("expected").getAsLong() : 0;
          long deadline = System.nanoTime() + TimeUnit.MILLISECONDS.toNanos(c.has("timeout_ms") ? c.get("timeout_ms").getAsLong() : 0);
          synchronized (rec) {
            while (rec.events.size() < expected && System.nanoTime() < deadline) {
              rec.wait(Math.max(1, TimeUnit.NANOSECONDS.toMillis(deadline - System.nanoTime())));
            }
            JsonArray events = new JsonArray();
            rec.events.forEach(events::add);
            reply.add("events", events);
            reply.add("threads", GSON.toJsonTree(rec.threads));
            reply.addProperty("active", rec.handle.isActive());
          }
        }
        break;
      case "cancel":
        watches.get(c.get("watch").getAsInt()).handle.cancel();
        break;
      case "drain":
        reply.addProperty("drained", drain(Duration.ofSeconds(10)));
        break;
      case "propose":
        {
          Message data = c.has("data_type") ? parse(str(c, "data_type"), c.get("data")) : null;
          int priority = c.has("priority") ? c.get("priority").getAsInt() : 0;
          Task t = proposeTask(str(c, "name"), data, priority);
          tasks.put(t.taskId(), t);
          reply.addProperty("task_id", t.taskId());
          reply.addProperty("state", t.state().name());
        }
        break;
      case "complete":
        taskComplete(str(c, "task_id"), TaskOutcome.valueOf(c.has("outcome") ? str(c, "outcome") : "SUCCEEDED"), str(c, "reason"));
        break;
      case "retract":
        retractTask(str(c, "task_id"));
        break;
      case "report": // the value as text: "NaN" and "Infinity" too, for the server to judge
        report(str(c, "name"), Double.parseDouble(str(c, "value")));
        break;
      case "rich_write":
        result(reply, add(str(c, "id"), Rich.canonical(str(c, "variant")), sa));
        break;
      case "rich_check":
        {
          RichEntry got = get(str(c, "id"), RichEntry.class, sa);
          List<String> diffs = Rich.diff(Rich.canonical(str(c, "variant")), got);
          reply.add("diffs", GSON.toJsonTree(diffs));
          reply.addProperty("equal", got.equals(Rich.canonical(str(c, "variant"))));
          // Write back what was read: the reverse direction of the round trip.
          if (c.has("echo_to")) {
            result(reply, add(str(c, "echo_to"), got, sa));
          }
        }
        break;
      case "add_async": // pipelined writes and large values: Streamed.java
        Streamed.addAsync(this, str(c, "prefix"), c.get("n").getAsInt(), reply);
        break;
      case "overwrite_async":
        Streamed.overwriteAsync(this, str(c, "id"), c.get("n").getAsInt(), reply);
        break;
      case "big_write":
        Streamed.bigWrite(this, str(c, "id"), sa, c.get("size").getAsInt(), reply);
        break;
      case "big_read":
        Streamed.bigRead(this, str(c, "id"), sa, reply);
        break;
      case "open_gate":
        gate.countDown();
        break;
      case "quit":
        requestStop();
        break;
      default:
        throw new cast.client.InvalidArgumentError("unknown command " + c.get("op"));
    }
  }

  @Override
  public void taskAdopted(Task task) {
    JsonObject o = new JsonObject();
    o.addProperty("task_id", task.taskId());
    o.addProperty("name", task.name());
    o.addProperty("priority", task.priority());
    o.addProperty("on_dispatcher", onDispatcherThread());
    event("adopted", o);
  }

  @Override
  public void taskRejected(Task task) {
    JsonObject o = new JsonObject();
    o.addProperty("task_id", task.taskId());
    o.addProperty("name", task.name());
    o.addProperty("reason", task.reason());
    event("rejected", o);
  }

  @Override
  public void watchFailed(CastError error) {
    JsonObject o = new JsonObject();
    o.addProperty("error", error.getClass().getSimpleName());
    o.addProperty("message", error.getMessage());
    event("watch_failed", o);
  }
}
