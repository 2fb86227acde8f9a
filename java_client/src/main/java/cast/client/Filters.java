package cast.client;

import com.google.protobuf.Message;
import java.util.EnumSet;

/**
 * The filter helpers of the component model (docs/design.md section 5), Java's form of the free
 * functions of the Python and C++ libraries. Import them statically to call them unqualified, as
 * JUnit 5's {@code Assertions}: {@code import static cast.client.Filters.localTypeFilter;} then
 * {@code onChange(localTypeFilter(Pose.class, Operation.ADD), this::onPose)}.
 */
public final class Filters {
  private Filters() {}

  private static EnumSet<Operation> ops(Operation... operations) {
    EnumSet<Operation> set = EnumSet.noneOf(Operation.class);
    if (operations != null) {
      for (Operation op : operations) {
        if (op == null) {
          throw new InvalidArgumentError("a filter's operations must not be null");
        }
        set.add(op);
      }
    }
    return set;
  }

  private static String checkedName(String s, String what) {
    if (s == null || s.isEmpty()) {
      throw new InvalidArgumentError(what + " must not be empty");
    }
    return s;
  }

  /** Changes to entries of type {@code cls} in the component's own SA (no operations: all). */
  public static ChangeFilter localTypeFilter(Class<? extends Message> cls, Operation... operations) {
    return localTypeFilter(Types.typeName(cls), operations);
  }

  /** Changes to entries of the type named {@code typeName} in the component's own SA. */
  public static ChangeFilter localTypeFilter(String typeName, Operation... operations) {
    return new ChangeFilter(ops(operations), checkedName(typeName, "the type name"), "", null, "", "", false);
  }

  /** Changes to entries of type {@code cls} in every SA. */
  public static ChangeFilter globalTypeFilter(Class<? extends Message> cls, Operation... operations) {
    return globalTypeFilter(Types.typeName(cls), operations);
  }

  /** Changes to entries of the type named {@code typeName} in every SA. */
  public static ChangeFilter globalTypeFilter(String typeName, Operation... operations) {
    return new ChangeFilter(ops(operations), checkedName(typeName, "the type name"), "", "", "", "", false);
  }

  /** Changes to one entry of the component's own SA. */
  public static ChangeFilter addressFilter(String id, Operation... operations) {
    return new ChangeFilter(ops(operations), "", checkedName(id, "the entry id"), null, "", "", false);
  }

  /** Changes to one entry of any SA. */
  public static ChangeFilter addressFilter(WorkingMemoryAddress address, Operation... operations) {
    return new ChangeFilter(
        ops(operations),
        "",
        checkedName(address.id(), "the entry id"),
        checkedName(address.subarchitecture(), "the address's subarchitecture"),
        "",
        "",
        false);
  }

  /** Changes made by one component, in every SA. */
  public static ChangeFilter sourceFilter(String componentId, Operation... operations) {
    return new ChangeFilter(ops(operations), "", "", "", checkedName(componentId, "the component id"), "", false);
  }

  /** Changes of the given operations in every SA (none given: every change); {@code .local()} for the own SA. */
  public static ChangeFilter operationFilter(Operation... operations) {
    return new ChangeFilter(ops(operations), "", "", "", "", "", false);
  }
}
