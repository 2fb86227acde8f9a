package cast.client;

import java.util.Collections;
import java.util.EnumSet;
import java.util.Set;

/**
 * Which change events a callback wants: every set field must match; an empty
 * field matches anything. Immutable: the {@code with...} methods return a new
 * filter. Build them with the helpers of {@link Filters} (statically imported,
 * or qualified: {@code Filters.localTypeFilter(...)}).
 *
 * <p>A "local" filter matches the component's own subarchitecture; the SA is
 * filled in when the filter is registered with {@code onChange}, so filters can
 * be made without a component.
 */
public final class ChangeFilter {
  private final Set<Operation> operations;
  private final String type;
  private final String id;
  private final String subarchitecture; // null: the registering component's own SA
  private final String sourceComponent;
  private final String sourceSubarchitecture;
  private final boolean includeEntry;

  ChangeFilter(
      Set<Operation> operations,
      String type,
      String id,
      String subarchitecture,
      String sourceComponent,
      String sourceSubarchitecture,
      boolean includeEntry) {
    this.operations =
        Collections.unmodifiableSet(
            operations.isEmpty() ? EnumSet.noneOf(Operation.class) : EnumSet.copyOf(operations));
    this.type = type == null ? "" : type;
    this.id = id == null ? "" : id;
    this.subarchitecture = subarchitecture;
    this.sourceComponent = sourceComponent == null ? "" : sourceComponent;
    this.sourceSubarchitecture = sourceSubarchitecture == null ? "" : sourceSubarchitecture;
    this.includeEntry = includeEntry;
  }

  /** The filter matching every change in every SA. */
  public static ChangeFilter any() {
    return new ChangeFilter(EnumSet.noneOf(Operation.class), "", "", "", "", "", false);
  }

  /** The operations matched (empty: every operation). */
  public Set<Operation> operations() {
    return operations;
  }

  /** The full message name matched ("" matches every type). */
  public String type() {
    return type;
  }

  /** The entry id matched ("" matches every id). */
  public String id() {
    return id;
  }

  /** The SA watched: "" for every SA, null for the registering component's own SA. */
  public String subarchitecture() {
    return subarchitecture;
  }

  /** Whether the filter watches the registering component's own SA. */
  public boolean isLocal() {
    return subarchitecture == null;
  }

  /** The writing component matched ("" matches every component). */
  public String sourceComponent() {
    return sourceComponent;
  }

  /** The writing component's SA matched ("" matches every SA). */
  public String sourceSubarchitecture() {
    return sourceSubarchitecture;
  }

  /** Whether events carry the entry. */
  public boolean includeEntry() {
    return includeEntry;
  }

  /** The same filter, asking for the entry in each event. */
  public ChangeFilter withEntry() {
    return new ChangeFilter(operations, type, id, subarchitecture, sourceComponent, sourceSubarchitecture, true);
  }

  /** The same filter, restricted to the given operations (none given: every operation). */
  public ChangeFilter withOperations(Operation... ops) {
    EnumSet<Operation> set = EnumSet.noneOf(Operation.class);
    Collections.addAll(set, ops);
    return new ChangeFilter(set, type, id, subarchitecture, sourceComponent, sourceSubarchitecture, includeEntry);
  }

  /** The same filter on the working memory of {@code sa} ("" for every SA). */
  public ChangeFilter inSubarchitecture(String sa) {
    if (sa == null) {
      throw new InvalidArgumentError("inSubarchitecture needs an SA name, or \"\" for every SA; use local() for the own SA");
    }
    return new ChangeFilter(operations, type, id, sa, sourceComponent, sourceSubarchitecture, includeEntry);
  }

  /** The same filter on the registering component's own SA. */
  public ChangeFilter local() {
    return new ChangeFilter(operations, type, id, null, sourceComponent, sourceSubarchitecture, includeEntry);
  }

  /** The same filter, matching only writes by components of {@code sa}. */
  public ChangeFilter fromSubarchitecture(String sa) {
    return new ChangeFilter(operations, type, id, subarchitecture, sourceComponent, sa, includeEntry);
  }

  @Override
  public boolean equals(Object o) {
    if (!(o instanceof ChangeFilter)) {
      return false;
    }
    ChangeFilter f = (ChangeFilter) o;
    return operations.equals(f.operations)
        && type.equals(f.type)
        && id.equals(f.id)
        && java.util.Objects.equals(subarchitecture, f.subarchitecture)
        && sourceComponent.equals(f.sourceComponent)
        && sourceSubarchitecture.equals(f.sourceSubarchitecture)
        && includeEntry == f.includeEntry;
  }

  @Override
  public int hashCode() {
    return java.util.Objects.hash(
        operations, type, id, subarchitecture, sourceComponent, sourceSubarchitecture, includeEntry);
  }

  @Override
  public String toString() {
    return "ChangeFilter(operations="
        + operations
        + " type='"
        + type
        + "' id='"
        + id
        + "' subarchitecture="
        + (subarchitecture == null ? "<own>" : "'" + subarchitecture + "'")
        + " source='"
        + sourceComponent
        + "' sourceSubarchitecture='"
        + sourceSubarchitecture
        + "' includeEntry="
        + includeEntry
        + ")";
  }
}
