package cast.rostest;

import cast.client.Args;
import cast.client.ChangeFilter;
import cast.client.Filters;
import cast.client.Operation;
import cast.client.UnmanagedComponent;
import cast.client.WorkingMemoryChange;
import com.google.protobuf.ByteString;
import java.time.Duration;
import java.util.HashMap;
import java.util.List;
import java.util.Map;
import java.util.TreeMap;
import java.util.function.Function;
import java.util.stream.Collectors;
import ros2.cast_test_msgs.msg.Reading;
import ros2.geometry_msgs.msg.Point;
import ros2.geometry_msgs.msg.PoseStamped;
import ros2.geometry_msgs.msg.Quaternion;
import ros2.geometry_msgs.msg.Twist;
import ros2.geometry_msgs.msg.Vector3;
import ros2.sensor_msgs.msg.Image;
import ros2.std_msgs.msg.Header;

/**
 * Reads bridged ROS 2 messages with the Java classes generated from `cast ros-types` output and
 * prints each as one JSON line with every field (an image's pixels as their size and FNV-1a hash,
 * other bytes as hex): "type", "id", then the fields. Args: watch, an object of entry type ->
 * {"sa": the WM, "count": stop after that many changes of the type}; the component stops once every
 * type has reached its count. Types: ros2.sensor_msgs.msg.Image, ros2.geometry_msgs.msg.PoseStamped,
 * ros2.cast_test_msgs.msg.Reading (the test's own package). With mode "command" it writes a
 * geometry_msgs/msg/Twist entry instead (overwritten every 300 ms until stopped, so that a ROS
 * subscriber discovered late gets it too).
 */
public class RosEntryCheck extends UnmanagedComponent {
  private static final Map<String, Function<WorkingMemoryChange, String>> FORMATS =
      Map.of(
          "ros2.sensor_msgs.msg.Image", RosEntryCheck::image,
          "ros2.geometry_msgs.msg.PoseStamped", RosEntryCheck::poseStamped,
          "ros2.cast_test_msgs.msg.Reading", RosEntryCheck::reading);

  private String mode;
  private String sa;
  private final Map<String, String> watchSa = new TreeMap<>();
  private final Map<String, Long> watchCount = new TreeMap<>();
  private final Map<String, Long> seen = new HashMap<>();

  @Override
  public void configure(Args args) {
    mode = args.getString("mode", "watch");
    sa = args.getString("sa", "motor");
    Args watch = args.getObject("watch");
    for (String type : watch.names()) {
      if (!FORMATS.containsKey(type)) {
        throw new IllegalArgumentException("args.watch: no decoder for type " + type);
      }
      Args spec = watch.getObject(type);
      if (!spec.has("sa") || !spec.has("count")) {
        throw new IllegalArgumentException("args.watch." + type + ": both \"sa\" and \"count\" are needed");
      }
      watchSa.put(type, spec.getString("sa", ""));
      watchCount.put(type, spec.getLong("count", 0));
    }
  }

  @Override
  public void start() {
    if (mode.equals("watch")) {
      for (Map.Entry<String, String> w : watchSa.entrySet()) {
        String type = w.getKey();
        ChangeFilter filter =
            Filters.globalTypeFilter(type, Operation.ADD, Operation.OVERWRITE)
                .inSubarchitecture(w.getValue())
                .withEntry();
        onChange(filter, change -> changed(type, change));
      }
    }
    System.out.println("{\"ready\":true}");
  }

  private synchronized void changed(String type, WorkingMemoryChange change) {
    long n = seen.getOrDefault(type, 0L);
    if (n >= watchCount.get(type)) {
      return; // one type's count reached: only the others now
    }
    System.out.println("{\"type\":" + quoted(type) + "," + FORMATS.get(type).apply(change).substring(1));
    System.out.flush();
    seen.put(type, n + 1);
    for (Map.Entry<String, Long> w : watchCount.entrySet()) {
      if (seen.getOrDefault(w.getKey(), 0L) < w.getValue()) {
        return;
      }
    }
    requestStop();
  }

  private static String image(WorkingMemoryChange change) {
    Image m = change.entry(Image.class).value();
    long stamp = m.getHeader().getStamp().getSec() * 1_000_000_000L + Integer.toUnsignedLong(
        m.getHeader().getStamp().getNanosec());
    long h = 0xcbf29ce484222325L;
    for (byte b : m.getData().toByteArray()) {
      h ^= (b & 0xff);
      h *= 0x100000001b3L;
    }
    return "{\"id\":" + quoted(change.id()) + ",\"frame_id\":" + quoted(m.getHeader().getFrameId())
        + ",\"stamp_ns\":" + stamp + ",\"height\":" + u32(m.getHeight()) + ",\"width\":" + u32(m.getWidth())
        + ",\"encoding\":" + quoted(m.getEncoding()) + ",\"is_bigendian\":" + u32(m.getIsBigendian())
        + ",\"step\":" + u32(m.getStep()) + ",\"size\":" + m.getData().size() + ",\"fnv\":"
        + quoted(Long.toHexString(h)) + "}";
  }

  private static String poseStamped(WorkingMemoryChange change) {
    PoseStamped m = change.entry(PoseStamped.class).value();
    Quaternion q = m.getPose().getOrientation();
    return "{\"id\":" + quoted(change.id()) + ",\"header\":" + header(m.getHeader()) + ",\"pose\":{\"position\":"
        + point(m.getPose().getPosition()) + ",\"orientation\":{\"x\":" + q.getX() + ",\"y\":" + q.getY()
        + ",\"z\":" + q.getZ() + ",\"w\":" + q.getW() + "}}}";
  }

  private static String reading(WorkingMemoryChange change) {
    Reading m = change.entry(Reading.class).value();
    return "{\"id\":" + quoted(change.id()) + ",\"header\":" + header(m.getHeader()) + ",\"level\":"
        + u32(m.getLevel()) + ",\"value\":" + m.getValue() + ",\"triple\":" + list(m.getTripleList(), String::valueOf)
        + ",\"label\":" + quoted(m.getLabel()) + ",\"points\":" + list(m.getPointsList(), RosEntryCheck::point)
        + ",\"gains\":" + list(m.getGainsList(), String::valueOf) + ",\"blob\":" + quoted(hex(m.getBlob()))
        + ",\"code\":" + quoted(hex(m.getCode())) + ",\"count\":" + m.getCount() + ",\"window\":{\"sec\":"
        + m.getWindow().getSec() + ",\"nanosec\":" + u32(m.getWindow().getNanosec()) + "}}";
  }

  private static String header(Header h) {
    return "{\"stamp\":{\"sec\":" + h.getStamp().getSec() + ",\"nanosec\":" + u32(h.getStamp().getNanosec())
        + "},\"frame_id\":" + quoted(h.getFrameId()) + "}";
  }

  // Double.toString: a text that reads back as the same double, -0.0 kept; Infinity and NaN as
  // Python's json reads them.
  private static String point(Point p) {
    return "{\"x\":" + p.getX() + ",\"y\":" + p.getY() + ",\"z\":" + p.getZ() + "}";
  }

  private static <T> String list(List<T> values, Function<T, String> format) {
    return values.stream().map(format).collect(Collectors.joining(",", "[", "]"));
  }

  /** A protobuf uint32 (a Java int) as the unsigned number it is. */
  private static String u32(int v) {
    return Integer.toUnsignedString(v);
  }

  private static String hex(ByteString data) {
    StringBuilder out = new StringBuilder();
    for (byte b : data.toByteArray()) {
      out.append(String.format("%02x", b & 0xff));
    }
    return out.toString();
  }

  // Not ASCII as \\u escapes: the output does not depend on the JVM's console encoding.
  private static String quoted(String s) {
    StringBuilder out = new StringBuilder("\"");
    for (char c : s.toCharArray()) {
      if (c == '"' || c == '\\') {
        out.append('\\').append(c);
      } else if (c < 0x20 || c > 0x7e) {
        out.append(String.format("\\u%04x", (int) c));
      } else {
        out.append(c);
      }
    }
    return out.append('"').toString();
  }

  @Override
  public void run() throws InterruptedException {
    if (!mode.equals("command")) {
      waitForStop();
      return;
    }
    Twist command =
        Twist.newBuilder()
            .setLinear(Vector3.newBuilder().setX(0.75).setY(-2.0).setZ(0.0))
            .setAngular(Vector3.newBuilder().setX(0.0).setY(0.0).setZ(-1.5e-7))
            .build();
    add("command", command, sa);
    System.out.println("{\"written\":true}");
    while (!waitForStop(Duration.ofMillis(300))) {
      overwrite("command", command, sa);
    }
  }
}
