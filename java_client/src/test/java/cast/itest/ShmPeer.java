package cast.itest;

import static cast.client.Filters.addressFilter;

import cast.client.Cast;
import cast.client.CastError;
import cast.client.ConnectOptions;
import cast.client.Connection;
import cast.client.LaunchContract;
import cast.client.Loan;
import cast.client.Operation;
import cast.client.Runner;
import cast.client.UnmanagedComponent;
import cast.client.ValueView;
import cast.client.WorkingMemoryChange;
import com.google.protobuf.ByteString;
import com.google.protobuf.BytesValue;
import java.io.IOException;
import java.io.InputStream;
import java.io.RandomAccessFile;
import java.nio.ByteBuffer;
import java.nio.ReadOnlyBufferException;
import java.nio.channels.FileChannel;
import java.nio.MappedByteBuffer;
import java.nio.file.Files;
import java.nio.file.Path;
import java.time.Duration;
import java.util.ArrayList;
import java.util.List;
import java.util.Scanner;

/**
 * A writer or a reader of large values as a process of its own: the Java twin of
 * tests/reliability/components/shm_peer.py and of the C++ cast_test_shm, with the same arguments
 * and lines, so that tests/interop/test_shared_memory_interop.py drives the peers of every
 * language alike. With the launch contract (CAST_*) in its environment:
 *
 * <ul>
 *   <li>{@code ShmPeer write N [change] [loan]}: adds "img" (or overwrites it if it exists) and
 *       overwrites it, N values of 1 MiB in all (value k is {@link #frame(int)}), printing {@code
 *       WROTE k} after each and {@code DONE} at the end; then it stays until killed or its stdin
 *       closes. {@code change}: once each write was acknowledged, it writes 0xFF over all of its
 *       staging area and prints {@code CHANGED k bytes} before {@code WROTE k}. {@code loan}: each
 *       value is made in a loan ({@code Component.loan}) and the loan written.
 *   <li>{@code ShmPeer read [hold|trywrite]}: watches "img" with its entry, printing {@code
 *       WATCHING} once the watch is confirmed and {@code GOT revision k shared same sum} per value:
 *       {@code k} which frame the view's field 1 is (-1: bytes that are no frame), {@code shared}
 *       1 if it came by shared memory, {@code same} 1 if the decoded entry has the view's bytes,
 *       {@code sum} a checksum of every byte read through the view ({@link #checksum}). {@code
 *       hold} keeps a view of every value; {@code trywrite} tries, on the first value lent, to
 *       write the memory it is in and prints {@code WRITE buffer=R pwrite=R mmap=R} (R: how it was
 *       refused, {@code allowed} if it was not: through the view's buffer, and through the memory
 *       file opened again read-write by its /proc path), then {@code AFTER k}. {@code FAILED
 *       reason} if the watch fails. It stays until killed or its stdin closes.
 *   <li>{@code ShmPeer get}: reads "img" with getView and get; prints {@code READ k shared same}.
 *   <li>{@code ShmPeer deadline SA MS}: two connections of its own ({@link Cast#connect} as
 *       {@code $CAST_COMPONENT_ID-get} and {@code -add} of {@code $CAST_SUBARCHITECTURE}, tokens
 *       minted from {@code $CAST_SECRET}, call timeout MS), with no shared-memory session yet (the
 *       add connection wrote a small value of the type in its own SA: the type is registered); prints {@code READY}, and at the line
 *       {@code go} a get and a 1 MiB add on SA at once, each {@code CALL get|add ErrorName|ok
 *       milliseconds}, then {@code CALLED}.
 * </ul>
 */
public final class ShmPeer extends UnmanagedComponent {
  static final int SIZE = 1 << 20;
  private static final int PERIOD = 253;

  private ShmPeer() {}

  /** The bytes of frame {@code k}: a pattern that differs in every byte position from frame to frame. */
  static byte[] frame(int k) {
    byte[] out = new byte[SIZE / PERIOD * PERIOD];
    for (int i = 0; i < out.length; i++) {
      out[i] = (byte) ((k * 7 + i % PERIOD) % PERIOD);
    }
    return out;
  }

  /** The {@code k} of a frame's bytes (read through the buffer, every byte), or -1. */
  static int which(ByteBuffer data) {
    if (data.remaining() != SIZE / PERIOD * PERIOD) {
      return -1;
    }
    int k = -1;
    for (int c = 0; c < 256 && k < 0; c++) {
      if (Byte.toUnsignedInt(data.get(data.position())) == (c * 7) % PERIOD
          && Byte.toUnsignedInt(data.get(data.position() + 1)) == (c * 7 + 1) % PERIOD) {
        k = c;
      }
    }
    if (k < 0) {
      return -1;
    }
    for (int i = 0; i < data.remaining(); i++) {
      if (Byte.toUnsignedInt(data.get(data.position() + i)) != (k * 7 + i % PERIOD) % PERIOD) {
        return -1;
      }
    }
    return k;
  }

  @Override
  public void watchFailed(CastError error) {
    System.out.println("FAILED " + error);
  }

  /** Every byte read: {@code sum = sum * 31 + byte} over the buffer, as cast_test_shm computes it. */
  static long checksum(ByteBuffer data) {
    long sum = 0;
    for (int i = data.position(); i < data.limit(); i++) {
      sum = sum * 31 + Byte.toUnsignedLong(data.get(i));
    }
    return sum;
  }

  /** How a write was refused: the error's errno name when the message has one. */
  private static String refusal(Exception e) {
    String m = String.valueOf(e.getMessage());
    if (m.contains("Operation not permitted")) {
      return "EPERM";
    }
    if (m.contains("Permission denied")) {
      return "EACCES";
    }
    return e.getClass().getSimpleName();
  }

  /** The /proc/self/map_files paths of this process's mappings of the server's {@code kind} memory files. */
  static List<Path> memoryFiles(String kind) throws IOException {
    List<Path> files = new ArrayList<>();
    for (String line : Files.readAllLines(Path.of("/proc/self/maps"))) {
      if (line.contains("memfd:cast-" + kind)) {
        files.add(Path.of("/proc/self/map_files/" + line.split(" ")[0]));
      }
    }
    return files;
  }

  /** Write 0xFF over every staging area this process has mapped; the bytes written. */
  static long changeStaging() throws IOException {
    long written = 0;
    for (Path area : memoryFiles("staging")) {
      try (RandomAccessFile file = new RandomAccessFile(area.toFile(), "rw")) {
        MappedByteBuffer map = file.getChannel().map(FileChannel.MapMode.READ_WRITE, 0, file.length());
        while (map.hasRemaining()) {
          map.put((byte) 0xFF);
        }
        written += file.length();
      }
    }
    return written;
  }

  /** Two fresh connections, then a get and a 1 MiB add at once at "go": how each ended, and when. */
  static void deadline(String sa, Duration timeout) throws InterruptedException {
    Connection getter = Cast.connect(options("get", timeout));
    Connection adder = Cast.connect(options("add", timeout));
    // The value's type is registered with every server by the first write of it: done now, in the
    // own SA, so that the add below meets the stopped server first when it opens the session.
    adder.add(System.getenv("CAST_COMPONENT_ID") + "-warm", BytesValue.of(ByteString.copyFromUtf8("warm")));
    say("READY");
    Scanner in = new Scanner(System.in);
    while (in.hasNextLine() && !in.nextLine().trim().equals("go")) {
      // until the test says go
    }
    BytesValue value = BytesValue.newBuilder().setValue(ByteString.copyFrom(frame(0))).build();
    Thread get = new Thread(() -> timed("get", () -> getter.get("deadline", BytesValue.class, sa)));
    Thread add = new Thread(() -> timed("add", () -> adder.add("deadline", value, sa)));
    get.start();
    add.start();
    get.join();
    add.join();
    say("CALLED");
    while (in.hasNextLine()) {
      in.nextLine();
    }
    getter.close();
    adder.close();
  }

  private static ConnectOptions options(String name, Duration timeout) {
    return new ConnectOptions()
        .componentId(System.getenv("CAST_COMPONENT_ID") + "-" + name)
        .subarchitecture(System.getenv("CAST_SUBARCHITECTURE"))
        .callTimeout(timeout);
  }

  private static void timed(String name, Runnable call) {
    long started = System.nanoTime();
    String outcome = "ok";
    try {
      call.run();
    } catch (CastError e) {
      outcome = e.getClass().getSimpleName();
    }
    say("CALL " + name + " " + outcome + " " + (System.nanoTime() - started) / 1_000_000);
  }

  /** Try to write the memory a lent value is in: through its buffer, and through its memory file. */
  static String tryWrite(ValueView view) throws IOException {
    StringBuilder out = new StringBuilder("WRITE");
    try {
      view.data().put(0, (byte) 0x55);
      out.append(" buffer=allowed");
    } catch (ReadOnlyBufferException e) {
      out.append(" buffer=ReadOnlyBufferException");
    }
    List<Path> files = memoryFiles("arena");
    if (files.isEmpty()) {
      return out.append(" pwrite=nofile mmap=nofile").toString();
    }
    try (RandomAccessFile file = new RandomAccessFile(files.get(0).toFile(), "rw")) {
      try {
        file.getChannel().write(ByteBuffer.wrap(new byte[] {0x55}), 0);
        out.append(" pwrite=allowed");
      } catch (IOException e) {
        out.append(" pwrite=").append(refusal(e));
      }
      try {
        file.getChannel().map(FileChannel.MapMode.READ_WRITE, 0, 4096);
        out.append(" mmap=allowed");
      } catch (IOException e) {
        out.append(" mmap=").append(refusal(e));
      }
    } catch (IOException e) {
      out.append(" pwrite=open:").append(refusal(e)).append(" mmap=open:").append(refusal(e));
    }
    return out.toString();
  }

  private static synchronized void say(String line) {
    System.out.println(line);
  }

  public static void main(String[] argv) throws Exception {
    if (argv[0].equals("deadline")) {
      deadline(argv[1], Duration.ofMillis(Long.parseLong(argv[2])));
      System.exit(0);
    }
    ShmPeer peer = Runner.connect(new ShmPeer(), LaunchContract.fromEnv());
    List<ValueView> held = new ArrayList<>();
    switch (argv[0]) {
      case "write" -> {
        int n = Integer.parseInt(argv[1]);
        List<String> options = List.of(argv).subList(2, argv.length);
        boolean change = options.contains("change");
        boolean loaned = options.contains("loan");
        for (int k = 0; k < n; k++) {
          boolean exists = k > 0 || peer.exists("img");
          if (loaned) {
            byte[] bytes = frame(k);
            Loan loan = peer.loan(BytesValue.getDefaultInstance(), "value", bytes.length);
            loan.buffer().put(bytes);
            if (exists) {
              peer.overwrite("img", loan);
            } else {
              peer.add("img", loan);
            }
          } else {
            BytesValue value = BytesValue.newBuilder().setValue(ByteString.copyFrom(frame(k))).build();
            if (exists) {
              peer.overwrite("img", value);
            } else {
              peer.add("img", value);
            }
          }
          if (change) {
            say("CHANGED " + k + " " + changeStaging());
          }
          say("WROTE " + k);
        }
        say("DONE");
      }
      case "read" -> {
        String option = argv.length > 1 ? argv[1] : "";
        boolean[] tried = {false};
        peer.onChange(
            addressFilter("img", Operation.ADD, Operation.OVERWRITE).withEntry(),
            (WorkingMemoryChange change) -> {
              ValueView view = change.view();
              ByteBuffer pixels = view.field(1);
              int k = which(pixels);
              boolean same = change.entry(BytesValue.class).value().getValue().asReadOnlyByteBuffer().equals(pixels);
              say("GOT " + change.revision() + " " + k + " " + (view.isShared() ? 1 : 0) + " " + (same ? 1 : 0) + " "
                  + Long.toUnsignedString(checksum(view.data())));
              if (option.equals("trywrite") && view.isShared() && !tried[0]) {
                tried[0] = true;
                say(tryWrite(view));
                say("AFTER " + which(view.field(1)));
              }
              if (option.equals("hold")) {
                held.add(view);
              } else {
                view.close();
              }
            });
        say("WATCHING");
      }
      case "get" -> {
        try (ValueView view = peer.getView("img")) {
          int k = which(view.field(1));
          boolean same = peer.get("img", BytesValue.class).getValue().asReadOnlyByteBuffer().equals(view.field(1));
          say("READ " + k + " " + (view.isShared() ? 1 : 0) + " " + (same ? 1 : 0));
        }
      }
      default -> {
        System.err.println("usage: ShmPeer write N [change] [loan] | read [hold|trywrite] | get | deadline SA MS");
        System.exit(2);
      }
    }
    InputStream in = System.in;
    try {
      while (in.read() >= 0) {
        // until the test closes stdin, or kills this process
      }
    } catch (IOException e) {
      // stdin gone: the same
    }
    peer.close();
    System.exit(0);
  }
}
