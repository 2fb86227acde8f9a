package cast.itest;

import cast.client.CastError;
import cast.client.LaunchContract;
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
import java.nio.file.Files;
import java.nio.file.Path;
import java.util.ArrayList;
import java.util.List;

/**
 * A writer or a reader of large values as a process of its own: the Java twin of
 * tests/reliability/components/shm_peer.py and of the C++ cast_test_shm, with the same arguments
 * and lines, so that tests/interop/test_shared_memory_interop.py drives the peers of every
 * language alike. With the launch contract (CAST_*) in its environment:
 *
 * <ul>
 *   <li>{@code ShmPeer write N}: adds "img" (or overwrites it if it exists) and overwrites it, N
 *       values of 1 MiB in all (value k is {@link #frame(int)}), printing {@code WROTE k} after
 *       each and {@code DONE} at the end; then it stays until killed or its stdin closes.
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

  /** Try to write the memory a lent value is in: through its buffer, and through its memory file. */
  static String tryWrite(ValueView view) throws IOException {
    StringBuilder out = new StringBuilder("WRITE");
    try {
      view.data().put(0, (byte) 0x55);
      out.append(" buffer=allowed");
    } catch (ReadOnlyBufferException e) {
      out.append(" buffer=ReadOnlyBufferException");
    }
    List<Path> files = new ArrayList<>();
    for (String line : Files.readAllLines(Path.of("/proc/self/maps"))) {
      if (line.contains("memfd:cast-arena")) {
        files.add(Path.of("/proc/self/map_files/" + line.split(" ")[0]));
      }
    }
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
    ShmPeer peer = Runner.connect(new ShmPeer(), LaunchContract.fromEnv());
    List<ValueView> held = new ArrayList<>();
    switch (argv[0]) {
      case "write" -> {
        int n = Integer.parseInt(argv[1]);
        for (int k = 0; k < n; k++) {
          BytesValue value = BytesValue.newBuilder().setValue(ByteString.copyFrom(frame(k))).build();
          if (k > 0 || peer.exists("img")) {
            peer.overwrite("img", value);
          } else {
            peer.add("img", value);
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
        System.err.println("usage: ShmPeer write N | read [hold|trywrite] | get");
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
