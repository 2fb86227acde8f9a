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
import java.nio.ByteBuffer;
import java.util.ArrayList;
import java.util.List;

/**
 * A writer or a reader of large values as a process of its own: the Java twin of
 * tests/reliability/components/shm_peer.py, with the same arguments and lines, so that
 * tests/interop/test_shared_memory_interop.py runs the peers of every language alike. With the
 * launch contract (CAST_*) in its environment:
 *
 * <ul>
 *   <li>{@code ShmPeer write N}: adds "img" (or overwrites it if it exists) and overwrites it, N
 *       values of 1 MiB in all (value k is {@link #frame(int)}), printing {@code WROTE k} after
 *       each and {@code DONE} at the end; then it stays until killed or its stdin closes.
 *   <li>{@code ShmPeer read [hold]}: watches "img" with its entry, printing {@code WATCHING} once
 *       the watch is confirmed and {@code GOT revision k shared} per value ({@code k}: which frame
 *       the view's bytes are, -1 for bytes that are no frame; {@code shared}: 1 if it came by shared
 *       memory). The decoded entry is checked against the view: {@code MISMATCH revision} if they
 *       differ. {@code hold} keeps a view of every value. {@code FAILED reason} if the watch
 *       fails. It stays until killed or its stdin closes.
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

  public static void main(String[] argv) throws Exception {
    ShmPeer peer = Runner.connect(new ShmPeer(), LaunchContract.fromEnv());
    List<ValueView> held = new ArrayList<>();
    if (argv[0].equals("write")) {
      int n = Integer.parseInt(argv[1]);
      for (int k = 0; k < n; k++) {
        BytesValue value = BytesValue.newBuilder().setValue(ByteString.copyFrom(frame(k))).build();
        if (k > 0 || peer.exists("img")) {
          peer.overwrite("img", value);
        } else {
          peer.add("img", value);
        }
        System.out.println("WROTE " + k);
      }
      System.out.println("DONE");
    } else {
      boolean hold = argv.length > 1 && argv[1].equals("hold");
      peer.onChange(
          addressFilter("img", Operation.ADD, Operation.OVERWRITE).withEntry(),
          (WorkingMemoryChange change) -> {
            ValueView view = change.view();
            int k = which(view.field(1));
            ByteString decoded = change.entry(BytesValue.class).value().getValue();
            synchronized (held) {
              if (!decoded.asReadOnlyByteBuffer().equals(view.field(1))) {
                System.out.println("MISMATCH " + change.revision());
              }
              System.out.println("GOT " + change.revision() + " " + k + " " + (view.isShared() ? 1 : 0));
              if (hold) {
                held.add(view);
              } else {
                view.close();
              }
            }
          });
      System.out.println("WATCHING");
    }
    System.out.flush();
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
