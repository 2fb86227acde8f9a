package cast.itest;

import cast.client.CastError;
import cast.client.Component;
import cast.client.Delivery;
import cast.client.Entry;
import cast.client.Priority;
import cast.client.WatchOptions;
import cast.client.WorkingMemoryChange;
import cast.client.WriteResult;
import cast.testing.CastTesting.Counter;
import com.google.gson.JsonArray;
import com.google.gson.JsonObject;
import com.google.protobuf.ByteString;
import com.google.protobuf.BytesValue;
import java.util.ArrayList;
import java.util.List;
import java.util.Locale;
import java.util.concurrent.CompletableFuture;
import java.util.concurrent.CompletionException;
import java.util.zip.CRC32;

/**
 * Driven's commands for the streamed write path: pipelined writes, large values and
 * the watch options. The same commands as cpp_client/tests/components/probe_streamed.cc, driven
 * by tests/interop/test_streamed_interop.py.
 */
final class Streamed {
  private Streamed() {}

  /** {@code n} addAsync calls (ids PREFIX-0 .. PREFIX-(n-1), Counters of value i), then waits for all. */
  static void addAsync(Component c, String prefix, int n, JsonObject reply) {
    List<CompletableFuture<WriteResult>> futures = new ArrayList<>();
    for (int i = 0; i < n; i++) {
      futures.add(c.addAsync(prefix + "-" + i, counter(c, i)));
    }
    settle(futures, reply);
  }

  /** {@code n} overwriteAsync calls of one entry (Counters of value 1 .. n), then waits for all. */
  static void overwriteAsync(Component c, String id, int n, JsonObject reply) {
    List<CompletableFuture<WriteResult>> futures = new ArrayList<>();
    for (int i = 1; i <= n; i++) {
      futures.add(c.overwriteAsync(id, counter(c, i)));
    }
    settle(futures, reply);
  }

  private static Counter counter(Component c, int value) {
    return Counter.newBuilder().setWriter(c.componentId()).setValue(value).build();
  }

  /** Revisions and versions in call order (0 for a refused write) and the refusals by index. */
  private static void settle(List<CompletableFuture<WriteResult>> futures, JsonObject reply) {
    JsonArray revisions = new JsonArray();
    JsonArray versions = new JsonArray();
    JsonArray errors = new JsonArray();
    for (int i = 0; i < futures.size(); i++) {
      try {
        WriteResult r = futures.get(i).join();
        revisions.add(r.revision());
        versions.add(r.version());
      } catch (CompletionException e) {
        if (!(e.getCause() instanceof CastError cause)) {
          throw e;
        }
        revisions.add(0);
        versions.add(0);
        JsonObject err = new JsonObject();
        err.addProperty("index", i);
        err.addProperty("error", cause.getClass().getSimpleName());
        err.addProperty("code", cause.code());
        errors.add(err);
      }
    }
    reply.add("revisions", revisions);
    reply.add("versions", versions);
    reply.add("errors", errors);
  }

  /** Adds a BytesValue of {@code size} bytes, byte i = i % 251. */
  static void bigWrite(Component c, String id, String sa, int size, JsonObject reply) {
    byte[] bytes = new byte[size];
    for (int i = 0; i < size; i++) {
      bytes[i] = (byte) (i % 251);
    }
    WriteResult r = c.add(id, BytesValue.of(ByteString.copyFrom(bytes)), sa);
    reply.addProperty("revision", r.revision());
    reply.addProperty("version", r.version());
    reply.addProperty("size", size);
    reply.addProperty("crc32", crc32(bytes));
  }

  /** Reads a BytesValue: its size and CRC-32, not its bytes. */
  static void bigRead(Component c, String id, String sa, JsonObject reply) {
    Entry<BytesValue> e = c.getEntry(id, BytesValue.class, sa);
    byte[] bytes = e.value().getValue().toByteArray();
    reply.addProperty("size", bytes.length);
    reply.addProperty("crc32", crc32(bytes));
    reply.addProperty("version", e.version());
    reply.addProperty("author", e.author());
  }

  /** A watch command's options: "delivery" (queue, latest) and "priority" (high, medium, low). */
  static WatchOptions options(JsonObject cmd) {
    WatchOptions o = WatchOptions.defaults();
    if (cmd.has("delivery")) {
      o = o.delivery(Delivery.valueOf(cmd.get("delivery").getAsString().toUpperCase(Locale.ROOT)));
    }
    if (cmd.has("priority")) {
      o = o.priority(Priority.valueOf(cmd.get("priority").getAsString().toUpperCase(Locale.ROOT)));
    }
    return o;
  }

  /** What a change says of latest delivery, and the size and CRC-32 of a BytesValue it carries. */
  static void describe(JsonObject event, WorkingMemoryChange ch) {
    event.addProperty("skipped", ch.skipped());
    event.addProperty("first_skipped_revision", ch.firstSkippedRevision());
    if (ch.hasEntry() && ch.type().equals("google.protobuf.BytesValue")) {
      byte[] bytes = ch.entry(BytesValue.class).value().getValue().toByteArray();
      event.addProperty("size", bytes.length);
      event.addProperty("crc32", crc32(bytes));
    }
  }

  static long crc32(byte[] bytes) {
    CRC32 crc = new CRC32();
    crc.update(bytes);
    return crc.getValue();
  }
}
