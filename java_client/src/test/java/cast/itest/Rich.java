package cast.itest;

import cast.testing.RichEntry;
import cast.testing.RichEntry.Colour;
import cast.testing.RichEntry.Point;
import cast.testing.RichEntry.Region;
import cast.testing.Shade;
import com.google.protobuf.ByteString;
import com.google.protobuf.Descriptors.FieldDescriptor;
import com.google.protobuf.Message;
import java.util.ArrayList;
import java.util.HashMap;
import java.util.Map;
import java.util.List;

/**
 * The canonical cast.testing.RichEntry of the type-fidelity tests. The same
 * values are built in Python by tests/interop/java_support.py (rich_entry);
 * keep the two in step.
 */
public final class Rich {
  private Rich() {}

  static Point point(double x, double y, double z) {
    return Point.newBuilder().setX(x).setY(y).setZ(z).build();
  }

  /** The canonical value; {@code variant} picks the oneof member: polygon, circle or name. */
  public static RichEntry canonical(String variant) {
    RichEntry.Builder b =
        RichEntry.newBuilder()
            .setText("Grüße, 世界 — ∑ 🚀 \u0000 end")
            .setBlob(ByteString.copyFrom(new byte[] {0, (byte) 0xff, (byte) 0xfe, (byte) 0x80, 0x7f, 1}))
            .setInt32Value(Integer.MIN_VALUE)
            .setInt64Min(Long.MIN_VALUE)
            .setInt64Max(Long.MAX_VALUE)
            .setUint32Value(-1) // 4294967295 as unsigned
            .setUint64Max(-1L) // 18446744073709551615 as unsigned
            .setSint64Value(-Long.MAX_VALUE)
            .setFixed64Value(-2L) // 18446744073709551614 as unsigned
            .setSfixed64Value(-1234567890123456789L)
            .setDoubleValue(3.141592653589793)
            .setDoubleTiny(Double.MIN_VALUE)
            .setDoubleHuge(Double.MAX_VALUE)
            .setDoubleInfinity(Double.NEGATIVE_INFINITY)
            .setFloatValue(0.1f)
            .setFlag(true)
            .setColour(Colour.COLOUR_BLUE)
            .setShade(Shade.SHADE_DARK)
            .setOrigin(point(1.5, -2.25, 1e-10))
            .setRegion(
                Region.newBuilder()
                    .setLabel("Zürich")
                    .addOutline(point(0, 0, 0))
                    .addOutline(point(1, 0, 0))
                    .setColour(Colour.COLOUR_GREEN)
                    .putAttributes("ключ", "значение")
                    .putAttributes("a", "")
                    .addChildren(Region.newBuilder().setLabel("child").setColour(Colour.COLOUR_RED)))
            .addTags("α")
            .addTags("")
            .addTags("tag")
            .addSamples(Long.MIN_VALUE)
            .addSamples(0)
            .addSamples(Long.MAX_VALUE)
            .addSamples(-1)
            .addWeights(0.5)
            .addWeights(-0.0)
            .addWeights(1e300)
            .addColours(Colour.COLOUR_RED)
            .addColours(Colour.COLOUR_GREEN)
            .addColours(Colour.COLOUR_BLUE)
            .addColours(Colour.COLOUR_UNSPECIFIED)
            .addRegions(Region.newBuilder().setLabel("r1"))
            .addRegions(Region.newBuilder().setLabel("r2").putAttributes("k", "v"))
            .putCounts("a", 1)
            .putCounts("negative", -5)
            .putCounts("max", Long.MAX_VALUE)
            .putPoints(Long.MIN_VALUE, point(1, 2, 3))
            .putPoints(0, Point.getDefaultInstance())
            .putPoints(42, point(-1, -1, -1))
            .putFlags(true, "yes")
            .putFlags(false, "no")
            .setMaybe(0);
    switch (variant) {
      case "circle":
        b.setCircleRadius(2.5);
        break;
      case "name":
        b.setShapeName("hexagon ⬡");
        break;
      case "polygon":
        b.setPolygon(Region.newBuilder().setLabel("poly").addOutline(point(1, 1, 0)));
        break;
      default:
        throw new IllegalArgumentException("unknown RichEntry variant " + variant);
    }
    return b.build();
  }

  /** A map field's entries as a Map: the wire (and reflection) order of map entries is not defined. */
  static Map<Object, Object> asMap(RichEntry m, FieldDescriptor fd) {
    Map<Object, Object> map = new HashMap<>();
    for (Object o : (List<?>) m.getField(fd)) {
      Message entry = (Message) o;
      FieldDescriptor key = entry.getDescriptorForType().findFieldByNumber(1);
      FieldDescriptor value = entry.getDescriptorForType().findFieldByNumber(2);
      map.put(entry.getField(key), entry.getField(value));
    }
    return map;
  }

  /** The names of the fields where {@code got} differs from {@code want} (value or presence). */
  public static List<String> diff(RichEntry want, RichEntry got) {
    List<String> diffs = new ArrayList<>();
    for (FieldDescriptor fd : RichEntry.getDescriptor().getFields()) {
      boolean presence = fd.hasPresence();
      if (presence && want.hasField(fd) != got.hasField(fd)) {
        diffs.add(fd.getName() + " (presence)");
      } else if (fd.isMapField() ? !asMap(want, fd).equals(asMap(got, fd)) : !want.getField(fd).equals(got.getField(fd))) {
        diffs.add(fd.getName());
      }
    }
    return diffs;
  }
}
