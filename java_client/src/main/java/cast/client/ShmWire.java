package cast.client;

import com.google.protobuf.CodedOutputStream;
import com.google.protobuf.MessageLite;
import java.io.FileDescriptor;
import java.io.IOException;
import java.nio.ByteBuffer;
import java.nio.ByteOrder;
import java.nio.charset.StandardCharsets;
import java.util.ArrayDeque;
import java.util.ArrayList;
import java.util.Collection;
import java.util.List;

/**
 * The frames of a shared-memory session on a server's Unix socket (docs/client-protocol.md,
 * "Large values by shared memory", "Frames"): a little-endian {@code u32} length of what
 * follows (1 to 65,536; up to 64 MiB for WRITES, REPLIES and EVENTS), a {@code u8} kind and its
 * fields. A frame that carries a memory file came with it as {@code SCM_RIGHTS}, no later than its
 * first byte: the {@link Reader} keeps the descriptors that arrive in order and gives the next one
 * to each frame of a kind that carries one. The twin of python/cast/wire/shared_memory.py. No sockets
 * here: {@link SharedSession} moves the bytes.
 */
final class ShmWire {
  private ShmWire() {}

  /**
   * The version this client says in HELLO: it needs nothing a later version adds, and uses NUDGE
   * only with a server whose WELCOME says {@link #NUDGE_VERSION} or later.
   */
  static final int HELLO_VERSION = 1;
  /** The first version whose servers answer NUDGE (WELCOME carries the server's version). */
  static final int NUDGE_VERSION = 2;

  // Client -> server.
  static final int HELLO = 1; // u16 version, then the token (UTF-8) to the end
  static final int RELEASE = 2; // n x u64 value ids given back
  static final int RECEIVED = 3; // u64 call, u64 count, u8 ended
  static final int WRITES = 4; // a serialized cast.v1.WriteRequests to the end
  static final int NUDGE = 5; // nothing; the server answers NUDGED (version 2)
  // Server -> client.
  static final int WELCOME = 10; // u16 version, 16 bytes session, 16 bytes server id, u64 threshold, window, staging
  static final int REFUSED = 11; // the reason (UTF-8) to the end; the server then closes
  static final int SEGMENT = 12; // u32 segment id, u64 size; carries the segment's memory file
  static final int RETIRE = 13; // u32 segment id
  static final int REPLIES = 14; // a serialized cast.v1.WriteReplies to the end
  static final int EVENTS = 15; // u64 call, then a serialized cast.v1.WatchResponse to the end
  static final int NUDGED = 16; // nothing: the answer to a NUDGE, which wakes a thread blocked in the socket's read

  /** The largest frame either side sends or accepts, but for the kinds that carry messages. */
  static final int MAX_FRAME = 1 << 16;
  /** The largest frame of a kind that carries a gRPC message (WRITES, REPLIES, EVENTS): 64 MiB, a message's limit. */
  static final int MAX_MESSAGE_FRAME = 64 << 20;
  /** Value ids one RELEASE frame carries at most (8 bytes each, within {@link #MAX_FRAME}). */
  static final int RELEASE_IDS = 8000;
  static final int WELCOME_BYTES = 2 + 16 + 16 + 8 + 8 + 8;

  /** A frame that breaks the protocol: the session ends. */
  static final class ProtocolError extends Exception {
    private static final long serialVersionUID = 1L;

    ProtocolError(String message) {
      super(message);
    }
  }

  /** One frame: its kind, its fields (after the kind byte, little-endian) and the memory file it carries, or null. */
  record Frame(int kind, ByteBuffer body, FileDescriptor fd) {}

  /** WELCOME's fields. */
  record Welcome(int version, byte[] session, byte[] serverId, long threshold, long window, long staging) {}

  private static ByteBuffer frame(int kind, int bodyBytes) {
    ByteBuffer b = ByteBuffer.allocate(5 + bodyBytes).order(ByteOrder.LITTLE_ENDIAN);
    b.putInt(1 + bodyBytes).put((byte) kind);
    return b;
  }

  /** HELLO: the protocol version and the caller's token. */
  static byte[] hello(String token) {
    byte[] text = token.getBytes(StandardCharsets.UTF_8);
    return frame(HELLO, 2 + text.length).putShort((short) HELLO_VERSION).put(text).array();
  }

  /** NUDGE: the server answers NUDGED (a fresh array each time: the caller's to send). */
  static byte[] nudge() {
    return frame(NUDGE, 0).array();
  }

  /** RELEASE frames for {@code valueIds} (one lease given back per id), {@link #RELEASE_IDS} a frame. */
  static List<byte[]> release(Collection<Long> valueIds) {
    List<byte[]> frames = new ArrayList<>();
    ByteBuffer b = null;
    int left = valueIds.size();
    for (long id : valueIds) {
      if (b == null) {
        b = frame(RELEASE, 8 * Math.min(left, RELEASE_IDS));
      }
      b.putLong(id);
      left--;
      if (!b.hasRemaining()) {
        frames.add(b.array());
        b = null;
      }
    }
    return frames;
  }

  /**
   * WRITES: {@code message} (a {@code cast.v1.WriteRequests}) serialized straight into the frame, so
   * that a value sent as bytes is copied once on its way to the socket; IllegalArgumentException
   * when the frame would be over {@link #MAX_MESSAGE_FRAME}.
   */
  static byte[] writes(MessageLite message) {
    int size = message.getSerializedSize();
    if (size + 1 > MAX_MESSAGE_FRAME) {
      throw new IllegalArgumentException(
          "a WRITES frame of " + (size + 1) + " bytes is over its bound of " + MAX_MESSAGE_FRAME + " bytes");
    }
    byte[] out = new byte[5 + size];
    ByteBuffer.wrap(out).order(ByteOrder.LITTLE_ENDIAN).putInt(1 + size).put((byte) WRITES);
    CodedOutputStream coded = CodedOutputStream.newInstance(out, 5, size);
    try {
      message.writeTo(coded);
    } catch (IOException e) { // an array of the message's own size: cannot run out of room
      throw new IllegalStateException("serializing a WRITES frame: " + e.getMessage(), e);
    }
    coded.checkNoSpaceLeft();
    return out;
  }

  /** RECEIVED: {@code count} references received on {@code call} so far; {@code ended}: the call is over. */
  static byte[] received(long call, long count, boolean ended) {
    return frame(RECEIVED, 17).putLong(call).putLong(count).put((byte) (ended ? 1 : 0)).array();
  }

  static Welcome parseWelcome(ByteBuffer body) throws ProtocolError {
    if (body.remaining() != WELCOME_BYTES) {
      throw new ProtocolError("WELCOME has " + body.remaining() + " bytes of fields, not " + WELCOME_BYTES);
    }
    int version = Short.toUnsignedInt(body.getShort());
    byte[] session = new byte[16];
    byte[] serverId = new byte[16];
    body.get(session).get(serverId);
    return new Welcome(version, session, serverId, body.getLong(), body.getLong(), body.getLong());
  }

  /** (segment id, size) of a SEGMENT. */
  static long[] parseSegment(ByteBuffer body) throws ProtocolError {
    if (body.remaining() != 12) {
      throw new ProtocolError("SEGMENT has the wrong size (" + body.remaining() + " bytes of fields)");
    }
    return new long[] {Integer.toUnsignedLong(body.getInt()), body.getLong()};
  }

  /** The segment id of a RETIRE. */
  static long parseRetire(ByteBuffer body) throws ProtocolError {
    if (body.remaining() != 4) {
      throw new ProtocolError("RETIRE has the wrong size (" + body.remaining() + " bytes of fields)");
    }
    return Integer.toUnsignedLong(body.getInt());
  }

  /** The text of a REFUSED. */
  static String text(ByteBuffer body) {
    return StandardCharsets.UTF_8.decode(body.duplicate()).toString();
  }

  static boolean carriesFd(int kind) {
    return kind == WELCOME || kind == SEGMENT;
  }

  /** The largest length (kind byte and fields) a frame of {@code kind} may have. */
  static int bound(int kind) {
    return kind == WRITES || kind == REPLIES || kind == EVENTS ? MAX_MESSAGE_FRAME : MAX_FRAME;
  }

  /** The call an EVENTS frame's body names; the body is then at its serialized WatchResponse. */
  static long parseEventsCall(ByteBuffer body) throws ProtocolError {
    if (body.remaining() < 8) {
      throw new ProtocolError("EVENTS has " + body.remaining() + " bytes of fields, fewer than its call's 8");
    }
    return body.getLong();
  }

  /** Bytes and descriptors in, as they were read; whole frames out, each with the descriptor it carries. */
  static final class Reader {
    private ByteBuffer buf = ByteBuffer.allocate(2 * MAX_FRAME).order(ByteOrder.LITTLE_ENDIAN);
    private final ArrayDeque<FileDescriptor> fds = new ArrayDeque<>();

    /** Add what one read gave ({@code n} bytes of {@code data} and the descriptors that came with them). */
    List<Frame> feed(byte[] data, int n, FileDescriptor[] received) throws ProtocolError {
      if (received != null) {
        for (FileDescriptor fd : received) {
          fds.add(fd);
        }
      }
      if (buf.remaining() < n) {
        ByteBuffer bigger = ByteBuffer.allocate(buf.position() + n + MAX_FRAME).order(ByteOrder.LITTLE_ENDIAN);
        buf.flip();
        bigger.put(buf);
        buf = bigger;
      }
      buf.put(data, 0, n);
      buf.flip();
      List<Frame> out = new ArrayList<>();
      try {
        while (buf.remaining() >= 5) {
          // The length is checked against its kind's bound as soon as the first five bytes are in.
          int length = buf.getInt(buf.position());
          int bound = bound(Byte.toUnsignedInt(buf.get(buf.position() + 4)));
          if (length < 1 || length > bound) {
            throw new ProtocolError("a frame of " + Integer.toUnsignedString(length) + " bytes of kind "
                + Byte.toUnsignedInt(buf.get(buf.position() + 4)) + " (1 to " + bound + " allowed)");
          }
          if (buf.remaining() - 4 < length) {
            break;
          }
          buf.position(buf.position() + 4);
          int kind = Byte.toUnsignedInt(buf.get());
          byte[] body = new byte[length - 1];
          buf.get(body);
          FileDescriptor fd = null;
          if (carriesFd(kind)) {
            fd = fds.poll();
            if (fd == null) {
              throw new ProtocolError("a frame of kind " + kind + " came without its memory file");
            }
          }
          out.add(new Frame(kind, ByteBuffer.wrap(body).order(ByteOrder.LITTLE_ENDIAN), fd));
        }
      } finally {
        buf.compact();
      }
      return out;
    }

    /**
     * Bytes still to come of the frame begun in what was fed (its length prefix counted while
     * incomplete); 0 when what was fed ended at a frame's end.
     */
    int wanted() {
      int held = buf.position(); // compacted after each feed: what is held starts at 0
      if (held == 0) {
        return 0;
      }
      if (held < 4) {
        return 4 - held;
      }
      // A length over its bound fails at the next feed; here it only sizes the next read.
      long frame = 4L + Integer.toUnsignedLong(buf.getInt(0));
      return (int) Math.min(Integer.MAX_VALUE, Math.max(0, frame - held));
    }

    /** Descriptors no frame claimed (to close). */
    List<FileDescriptor> stray() {
      List<FileDescriptor> left = new ArrayList<>(fds);
      fds.clear();
      return left;
    }
  }
}
