package cast.bench;

import cast.client.CastError;
import cast.client.Component;
import cast.client.Filters;
import cast.client.LaunchContract;
import cast.client.Operation;
import cast.client.Runner;
import cast.client.UnmanagedComponent;
import cast.client.ValueView;
import cast.client.WatchOptions;
import com.google.protobuf.ByteString;
import com.google.protobuf.BytesValue;
import java.io.BufferedReader;
import java.io.IOException;
import java.io.InputStreamReader;
import java.nio.ByteBuffer;
import java.nio.ByteOrder;
import java.nio.charset.StandardCharsets;
import java.util.ArrayList;
import java.util.List;
import java.util.Map;
import java.util.TreeMap;
import java.util.concurrent.CountDownLatch;
import java.util.concurrent.TimeUnit;

/**
 * The Java client's side of benchmark M7 (bench/other_clients.py), measured like
 * the Python client in bench/cast_cases.py (m1_sequential, m3_latency). A test
 * class, not part of the library: {@code make java} compiles it into
 * target/test-classes, and the benchmark runs
 * {@code java -cp target/cast-client-all.jar:target/test-classes cast.bench.Bench MODE ...}
 * with the launch contract (CAST_ENDPOINT, CAST_COMPONENT_ID, CAST_SUBARCHITECTURE,
 * CAST_TOKEN) in its environment. Modes:
 *
 * <ul>
 *   <li>{@code add N}: 200 warm-up adds, then N sequential adds of a 100-byte
 *       google.protobuf.BytesValue; prints {"calls": N, "seconds": S, "per_s": R}.
 *   <li>{@code blocks WARM}: WARM warm-up adds, then prints "ready" and reads stdin: for
 *       each line "B W", W untimed adds, then B sequential adds and one line with the seconds
 *       they took; ends at EOF (bench/other_clients.py interleaves these blocks with the
 *       other languages').
 *   <li>{@code watch N}: onChange(addressFilter("lat")) in its SA; prints "ready" once
 *       the watch is confirmed, then after N events {"REVISION": NS, ...}, NS the
 *       System.nanoTime() (CLOCK_MONOTONIC) in the callback.
 *   <li>{@code write N GAP_MS [WARM [TURN SIDES]]}: adds "lat", WARM overwrites back to back (not
 *       measured), then N-1 overwrites spaced by GAP_MS, stamping System.nanoTime() just before
 *       each; prints {"REVISION": NS, ...} of the measured ones. With TURN (1..SIDES) every
 *       overwrite is in its turn ({@link #waitForTurn}; M7 measures the three languages'
 *       latencies so).
 *   <li>{@code image-write SIZE N GAP_US}: (bench/shared_memory.py) adds "img", a BytesValue of SIZE
 *       bytes, and overwrites it N times, the i-th at start + i * GAP_US (0: back to back), each made
 *       and then stamped on System.nanoTime() just before it; then deletes it (the watchers' end mark) and prints
 *       {"REVISION": NS, ...} of the overwrites. The same as bench/image_writer.py.
 *   <li>{@code image-watch queue|latest}: (M8, bench/images.py; bench/shared_memory.py)
 *       onChange(addressFilter("img") with the entry, WatchOptions with that delivery); prints
 *       "ready", then at the DELETE of "img" one line {"stamps": {"REVISION": NS, ...}, "bytes": B,
 *       "events": E, "skipped": S, "checksum": C, "shared": N}: every overwrite received, the
 *       value bytes, the events received (the add and the delete too), what a latest watch
 *       skipped, the sum of the checksums of the values and how many came by shared memory. Each
 *       value is read through its {@link ValueView} (shared memory on the server's host, not
 *       copied): every byte of its {@code bytes} field goes into its checksum ({@link #checksum})
 *       before the stamp is taken.
 * </ul>
 *
 * <p>On Linux System.nanoTime() reads CLOCK_MONOTONIC, shared by every process of
 * the machine, so the stamps compare with the other process's and with Python's
 * time.perf_counter_ns.
 */
public final class Bench {
  /** Counted down at the end of an image watch: its DELETE, or the watch failing. */
  private static final CountDownLatch WATCH_ENDED = new CountDownLatch(1);

  private static final BytesValue VALUE =
      BytesValue.newBuilder().setValue(ByteString.copyFromUtf8("x".repeat(100))).build();

  private Bench() {}

  public static void main(String[] argv) throws Exception {
    if (argv.length < 2 || (argv[0].equals("write") && argv.length < 3)) {
      System.err.println(
          "usage: Bench add N | blocks WARM | watch N | write N GAP_MS [WARM [TURN SIDES]]"
              + " | image-watch queue|latest"
              + " | image-write SIZE N GAP_US"
              + " (with the CAST_* launch environment)");
      System.exit(2);
    }
    int n = argv[0].equals("image-watch") ? 0 : Integer.parseInt(argv[1]);
    if (argv[0].equals("image-write") && argv.length < 4) {
      System.err.println("usage: Bench image-write SIZE N GAP_US");
      System.exit(2);
    }
    UnmanagedComponent c =
        Runner.connect(
            new UnmanagedComponent() {
              @Override
              public void watchFailed(CastError error) throws Exception {
                super.watchFailed(error);
                WATCH_ENDED.countDown(); // image-watch ends now rather than at its timeout
              }
            },
            LaunchContract.fromEnv());
    try {
      switch (argv[0]) {
        case "add" -> add(c, n, argv.length > 2 ? Integer.parseInt(argv[2]) : 200);
        case "blocks" -> blocks(c, n);
        case "watch" -> watch(c, n);
        case "write" ->
            write(
                c,
                n,
                Long.parseLong(argv[2]),
                argv.length > 3 ? Integer.parseInt(argv[3]) : 0,
                argv.length > 4 ? Integer.parseInt(argv[4]) : 0,
                argv.length > 5 ? Integer.parseInt(argv[5]) : 2);
        case "image-watch" -> imageWatch(c, argv[1]);
        case "image-write" -> imageWrite(c, n, Integer.parseInt(argv[2]), Long.parseLong(argv[3]));
        default -> {
          System.err.println("unknown mode " + argv[0]);
          System.exit(2);
        }
      }
    } finally {
      c.close();
    }
    System.exit(0);
  }

  private static void add(Component c, int n, int warm) {
    // Ids made up front, as the Python benchmark does, so only the call is timed.
    List<String> ids = new ArrayList<>(warm + n);
    for (int i = 0; i < warm + n; i++) {
      ids.add(c.componentId() + "-" + i);
    }
    for (int i = 0; i < warm; i++) {
      c.add(ids.get(i), VALUE);
    }
    long start = System.nanoTime();
    for (int i = warm; i < warm + n; i++) {
      c.add(ids.get(i), VALUE);
    }
    double seconds = (System.nanoTime() - start) / 1e9;
    System.out.println("{\"calls\": " + n + ", \"seconds\": " + seconds + ", \"per_s\": " + n / seconds + "}");
  }

  private static void blocks(Component c, int warm) throws IOException {
    long next = 0;
    for (int i = 0; i < warm; i++) {
      c.add(c.componentId() + "-" + next++, VALUE);
    }
    System.out.println("ready");
    System.out.flush();
    BufferedReader in = new BufferedReader(new InputStreamReader(System.in, StandardCharsets.UTF_8));
    for (String line = in.readLine(); line != null; line = in.readLine()) {
      String[] words = line.trim().split("\\s+");
      int b = Integer.parseInt(words[0]);
      int w = words.length > 1 ? Integer.parseInt(words[1]) : 0;
      for (int i = 0; i < w; i++) {
        c.add(c.componentId() + "-" + next++, VALUE);
      }
      // Ids made before the clock starts, so only the calls are timed.
      List<String> ids = new ArrayList<>(b);
      for (int i = 0; i < b; i++) {
        ids.add(c.componentId() + "-" + next++);
      }
      long start = System.nanoTime();
      for (String id : ids) {
        c.add(id, VALUE);
      }
      System.out.println((System.nanoTime() - start) / 1e9);
      System.out.flush();
    }
  }

  private static void watch(Component c, int n) throws InterruptedException {
    Map<Long, Long> stamps = new TreeMap<>();
    CountDownLatch done = new CountDownLatch(1);
    c.onChange(
        Filters.addressFilter("lat"),
        change -> {
          long t = System.nanoTime();
          synchronized (stamps) {
            stamps.put(change.revision(), t);
            if (stamps.size() >= n) {
              done.countDown();
            }
          }
        });
    System.out.println("ready");
    System.out.flush();
    done.await(120, TimeUnit.SECONDS);
    synchronized (stamps) {
      System.out.println(json(stamps));
    }
  }

  private static void write(Component c, int n, long gapMs, int warm, int turn, int sides)
      throws InterruptedException {
    Map<Long, Long> sent = new TreeMap<>();
    c.add("lat", VALUE);
    for (int i = 0; i < warm; i++) {
      waitForTurn(turn, sides);
      c.overwrite("lat", VALUE);
    }
    for (int i = 0; i < n - 1; i++) {
      Thread.sleep(gapMs);
      waitForTurn(turn, sides);
      long t0 = System.nanoTime();
      sent.put(c.overwrite("lat", VALUE).revision(), t0);
    }
    System.out.println(json(sent));
    c.deleteEntry("lat"); // so that another run on this server can add it again
  }

  private static final long SECOND_NS = 1_000_000_000L;
  private static final long TURN_SKIP_NS = 70_000_000L;

  /**
   * Sleeps until turn {@code turn} of {@code sides} may write (bench/turns.py): the seconds of
   * CLOCK_MONOTONIC whose number modulo {@code sides} is {@code turn - 1}, from 70 ms into each, so
   * that the side before has been read. Turn 0: no turn.
   */
  static void waitForTurn(int turn, int sides) throws InterruptedException {
    if (turn == 0) {
      return;
    }
    long now = System.nanoTime();
    long begin = turnStart(turn, sides, now);
    while (now < begin) {
      long left = begin - now;
      Thread.sleep(left / 1_000_000L, (int) (left % 1_000_000L));
      now = System.nanoTime();
    }
  }

  /** The first moment at or after {@code ns} in the turn's writing time (bench.turns.next_start). */
  static long turnStart(int turn, int sides, long ns) {
    long second = ns / SECOND_NS;
    long mine = turn - 1;
    if (second % sides == mine) {
      return ns % SECOND_NS >= TURN_SKIP_NS ? ns : second * SECOND_NS + TURN_SKIP_NS;
    }
    long ahead = Math.floorMod(mine - second % sides, (long) sides);
    return (second + ahead) * SECOND_NS + TURN_SKIP_NS;
  }

  private static void imageWrite(Component c, int size, int frames, long gapMicros) throws InterruptedException {
    List<byte[]> fills = new ArrayList<>(); // made before the clock starts
    for (int k = 0; k < 2; k++) {
      byte[] b = new byte[size];
      java.util.Arrays.fill(b, (byte) (k + 1)); // never 0: a watcher that read no byte cannot match
      fills.add(b);
    }
    c.add("img", BytesValue.newBuilder().setValue(ByteString.copyFrom(fills.get(0))).build());
    Map<Long, Long> sent = new TreeMap<>();
    long start = System.nanoTime();
    for (int i = 0; i < frames; i++) {
      if (gapMicros > 0) {
        long delay = start + i * gapMicros * 1000 - System.nanoTime();
        if (delay > 0) {
          TimeUnit.NANOSECONDS.sleep(delay);
        }
      }
      // Made (its bytes copied) just before its stamp, as the peers' publisher makes its payload
      // (bench.peer_fanout.drive): a fresh frame is in the cache when it is published.
      BytesValue value = BytesValue.newBuilder().setValue(ByteString.copyFrom(fills.get(i % 2))).build();
      long t = System.nanoTime();
      sent.put(c.overwrite("img", value).revision(), t);
    }
    c.deleteEntry("img");
    System.out.println(json(sent));
  }

  /**
   * The checksum of a value as the benchmark's watchers compute it: the sum, modulo 2**64, of its
   * little-endian 64-bit words (a last partial word as its bytes, each a word of its own).
   */
  static long checksum(ByteBuffer data) {
    ByteBuffer b = data.slice().order(ByteOrder.LITTLE_ENDIAN);
    long sum = 0;
    int words = b.remaining() / 8 * 8;
    for (int i = 0; i < words; i += 8) {
      sum += b.getLong(i);
    }
    for (int i = words; i < b.remaining(); i++) {
      sum += Byte.toUnsignedLong(b.get(i));
    }
    return sum;
  }

  private static void imageWatch(Component c, String delivery) throws InterruptedException {
    Map<Long, Long> stamps = new TreeMap<>();
    long[] totals = new long[5]; // bytes, events, skipped, checksums, values by shared memory
    CountDownLatch ended = WATCH_ENDED;
    // The checksum compiled before the first frame, on the kind of buffer a view gives (direct,
    // read-only): interpreted, it reads 6 MiB in a good part of a second and the watcher falls
    // behind the server's history.
    ByteBuffer warm = ByteBuffer.allocateDirect(1 << 20).asReadOnlyBuffer();
    long warmSum = 0;
    for (int i = 0; i < 50; i++) {
      warmSum += checksum(warm);
    }
    System.err.println("checksum warmed up (" + warmSum + ")");
    WatchOptions options = delivery.equals("latest") ? WatchOptions.latest() : WatchOptions.queue();
    c.onChange(
        Filters.addressFilter("img").withEntry(),
        change -> {
          int size = 0;
          long sum = 0;
          boolean shared = false;
          long t = 0;
          if (change.operation() != Operation.DELETE) {
            try (ValueView view = change.view()) { // read in place: every byte, nothing copied
              ByteBuffer pixels = view.field(1);
              size = pixels.remaining();
              sum = checksum(pixels);
              // Every byte read: the stamp, before the value is given back (as the C++ watcher and
              // the peers' subscribers stamp before they let their buffer go).
              t = System.nanoTime();
              shared = view.isShared();
            }
          }
          synchronized (stamps) {
            totals[1] += 1;
            totals[2] += change.skipped();
            if (change.operation() == Operation.OVERWRITE) {
              stamps.put(change.revision(), t);
              totals[0] += size;
              totals[3] += sum;
              totals[4] += shared ? 1 : 0;
            }
          }
          if (change.operation() == Operation.DELETE) {
            ended.countDown();
          }
        },
        options);
    System.out.println("ready");
    System.out.flush();
    ended.await(300, TimeUnit.SECONDS);
    synchronized (stamps) {
      System.out.println(
          "{\"stamps\": " + json(stamps) + ", \"bytes\": " + totals[0] + ", \"events\": " + totals[1]
              + ", \"skipped\": " + totals[2] + ", \"checksum\": " + Long.toUnsignedString(totals[3])
              + ", \"shared\": " + totals[4] + "}");
    }
  }

  private static String json(Map<Long, Long> stamps) {
    StringBuilder out = new StringBuilder("{");
    for (Map.Entry<Long, Long> e : stamps.entrySet()) {
      if (out.length() > 1) {
        out.append(", ");
      }
      out.append('"').append(e.getKey()).append("\": ").append(e.getValue());
    }
    return out.append('}').toString();
  }
}
