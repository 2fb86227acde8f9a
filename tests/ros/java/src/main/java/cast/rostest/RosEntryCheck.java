package cast.rostest;

import cast.client.Args;
import cast.client.ChangeFilter;
import cast.client.Filters;
import cast.client.Operation;
import cast.client.UnmanagedComponent;
import cast.client.WorkingMemoryChange;
import java.time.Duration;
import ros2.geometry_msgs.msg.Twist;
import ros2.geometry_msgs.msg.Vector3;
import ros2.sensor_msgs.msg.Image;

/**
 * Reads bridged ROS 2 images with the Java classes generated from `cast ros-types` output, printing
 * each as one JSON line (every field, and an FNV-1a hash of the pixels); or, with mode "command",
 * writes a geometry_msgs/msg/Twist entry (overwritten every 300 ms until stopped, so that a ROS
 * subscriber discovered late gets it too).
 */
public class RosEntryCheck extends UnmanagedComponent {
  private String mode;
  private String sa;
  private int count;

  @Override
  public void configure(Args args) {
    mode = args.getString("mode", "images");
    sa = args.getString("sa", "vision");
    count = args.getInt("count", 1);
  }

  @Override
  public void start() {
    if (mode.equals("images")) {
      ChangeFilter filter =
          Filters.globalTypeFilter(Image.class, Operation.ADD, Operation.OVERWRITE)
              .inSubarchitecture(sa)
              .withEntry();
      onChange(filter, this::image);
    }
    System.out.println("{\"ready\":true}");
  }

  private int seen;

  private void image(WorkingMemoryChange change) {
    Image m = change.entry(Image.class).value();
    long stamp = m.getHeader().getStamp().getSec() * 1_000_000_000L + m.getHeader().getStamp().getNanosec();
    long h = 0xcbf29ce484222325L;
    for (byte b : m.getData().toByteArray()) {
      h ^= (b & 0xff);
      h *= 0x100000001b3L;
    }
    System.out.printf(
        "{\"id\":\"%s\",\"frame_id\":\"%s\",\"stamp_ns\":%d,\"height\":%d,\"width\":%d,\"encoding\":\"%s\","
            + "\"is_bigendian\":%d,\"step\":%d,\"size\":%d,\"fnv\":\"%s\"}%n",
        change.id(), m.getHeader().getFrameId(), stamp, m.getHeight(), m.getWidth(), m.getEncoding(),
        m.getIsBigendian(), m.getStep(), m.getData().size(), Long.toHexString(h));
    System.out.flush();
    if (++seen >= count) {
      requestStop();
    }
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
