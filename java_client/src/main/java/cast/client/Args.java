package cast.client;

import com.google.protobuf.InvalidProtocolBufferException;
import com.google.protobuf.Struct;
import com.google.protobuf.Value;
import com.google.protobuf.util.JsonFormat;
import java.util.ArrayList;
import java.util.LinkedHashMap;
import java.util.List;
import java.util.Map;
import java.util.Set;

/**
 * A component's arguments: the {@code args} object of its configuration entry,
 * passed to {@code configure}. Read them with typed getters that take a default;
 * a value of the wrong JSON type is an InvalidArgumentError naming it.
 *
 * <p>JSON numbers are doubles: integers beyond 2^53 lose precision, so pass such
 * values as strings.
 */
public final class Args {
  private final Struct struct;

  /** Arguments from a protobuf Struct. */
  public Args(Struct struct) {
    this.struct = struct;
  }

  /** No arguments. */
  public static Args empty() {
    return new Args(Struct.getDefaultInstance());
  }

  /** Arguments from a JSON object; InvalidArgumentError if the text is not one. */
  public static Args fromJson(String json) {
    String text = json == null || json.isBlank() ? "{}" : json.trim();
    if (!text.startsWith("{")) {
      throw new InvalidArgumentError("component arguments must be a JSON object, got: " + abbreviate(text));
    }
    Struct.Builder b = Struct.newBuilder();
    try {
      JsonFormat.parser().merge(text, b);
    } catch (InvalidProtocolBufferException | RuntimeException e) {
      throw new InvalidArgumentError("component arguments are not valid JSON: " + e.getMessage());
    }
    return new Args(b.build());
  }

  private static String abbreviate(String s) {
    return s.length() > 60 ? s.substring(0, 57) + "..." : s;
  }

  /** The arguments as a protobuf Struct. */
  public Struct toStruct() {
    return struct;
  }

  /** The argument names. */
  public Set<String> names() {
    return struct.getFieldsMap().keySet();
  }

  /** Whether an argument is given (a JSON null counts as given). */
  public boolean has(String name) {
    return struct.containsFields(name);
  }

  private Value value(String name, Value.KindCase kind, String what) {
    Value v = struct.getFieldsOrDefault(name, null);
    if (v == null || v.getKindCase() == Value.KindCase.NULL_VALUE) {
      return null;
    }
    if (v.getKindCase() != kind) {
      throw new InvalidArgumentError(
          "argument '" + name + "' must be " + what + ", got " + toJava(v) + " (" + describe(v) + ")");
    }
    return v;
  }

  private static String describe(Value v) {
    switch (v.getKindCase()) {
      case NUMBER_VALUE:
        return "a number";
      case STRING_VALUE:
        return "a string";
      case BOOL_VALUE:
        return "a boolean";
      case LIST_VALUE:
        return "a list";
      case STRUCT_VALUE:
        return "an object";
      default:
        return "null";
    }
  }

  /** A string argument, or {@code dflt} if absent. */
  public String getString(String name, String dflt) {
    Value v = value(name, Value.KindCase.STRING_VALUE, "a string");
    return v == null ? dflt : v.getStringValue();
  }

  /** A number argument, or {@code dflt} if absent. */
  public double getDouble(String name, double dflt) {
    Value v = value(name, Value.KindCase.NUMBER_VALUE, "a number");
    return v == null ? dflt : v.getNumberValue();
  }

  /** An integer argument, or {@code dflt} if absent; InvalidArgumentError for a fraction. */
  public long getLong(String name, long dflt) {
    Value v = value(name, Value.KindCase.NUMBER_VALUE, "an integer");
    if (v == null) {
      return dflt;
    }
    double d = v.getNumberValue();
    if (d != Math.rint(d) || Double.isInfinite(d)) {
      throw new InvalidArgumentError("argument '" + name + "' must be an integer, got " + d);
    }
    return (long) d;
  }

  /** An integer argument that fits an int, or {@code dflt} if absent. */
  public int getInt(String name, int dflt) {
    long l = getLong(name, dflt);
    if (l < Integer.MIN_VALUE || l > Integer.MAX_VALUE) {
      throw new InvalidArgumentError("argument '" + name + "' is out of the int range: " + l);
    }
    return (int) l;
  }

  /** A boolean argument, or {@code dflt} if absent. */
  public boolean getBoolean(String name, boolean dflt) {
    Value v = value(name, Value.KindCase.BOOL_VALUE, "true or false");
    return v == null ? dflt : v.getBoolValue();
  }

  /** A list argument as Java values (see {@link #asMap}), or an empty list if absent. */
  public List<Object> getList(String name) {
    Value v = value(name, Value.KindCase.LIST_VALUE, "a list");
    if (v == null) {
      return List.of();
    }
    @SuppressWarnings("unchecked")
    List<Object> list = (List<Object>) toJava(v);
    return list;
  }

  /** An object argument as nested Args, or empty Args if absent. */
  public Args getObject(String name) {
    Value v = value(name, Value.KindCase.STRUCT_VALUE, "an object");
    return v == null ? empty() : new Args(v.getStructValue());
  }

  /**
   * The arguments as plain Java values: String, Double, Boolean, null, List and
   * Map (insertion order of the JSON is not kept).
   */
  public Map<String, Object> asMap() {
    Map<String, Object> m = new LinkedHashMap<>();
    struct.getFieldsMap().forEach((k, v) -> m.put(k, toJava(v)));
    return m;
  }

  static Object toJava(Value v) {
    switch (v.getKindCase()) {
      case NUMBER_VALUE:
        return v.getNumberValue();
      case STRING_VALUE:
        return v.getStringValue();
      case BOOL_VALUE:
        return v.getBoolValue();
      case LIST_VALUE:
        List<Object> list = new ArrayList<>();
        for (Value item : v.getListValue().getValuesList()) {
          list.add(toJava(item));
        }
        return list;
      case STRUCT_VALUE:
        return new Args(v.getStructValue()).asMap();
      default:
        return null;
    }
  }

  @Override
  public String toString() {
    return "Args" + asMap();
  }
}
