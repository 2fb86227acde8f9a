package cast.client;

/**
 * How an {@code onChange} watch is delivered: {@link Delivery} (QUEUE, the default, or
 * LATEST) and the {@link Priority} of its callbacks on the component's dispatcher (MEDIUM by
 * default). Immutable; each method returns a new value:
 * {@code onChange(filter, this::onImage, WatchOptions.latest().priority(Priority.HIGH))}.
 */
public final class WatchOptions {
  private static final WatchOptions DEFAULTS = new WatchOptions(Delivery.QUEUE, Priority.MEDIUM);

  private final Delivery delivery;
  private final Priority priority;

  private WatchOptions(Delivery delivery, Priority priority) {
    if (delivery == null || priority == null) {
      throw new InvalidArgumentError("watch options: delivery and priority must not be null");
    }
    this.delivery = delivery;
    this.priority = priority;
  }

  /** Every change in order, at MEDIUM priority: what {@code onChange} without options does. */
  public static WatchOptions defaults() {
    return DEFAULTS;
  }

  /** Every change in order ({@link Delivery#QUEUE}), at MEDIUM priority. */
  public static WatchOptions queue() {
    return DEFAULTS;
  }

  /** Only the newest undelivered change of each entry ({@link Delivery#LATEST}), at MEDIUM priority. */
  public static WatchOptions latest() {
    return new WatchOptions(Delivery.LATEST, Priority.MEDIUM);
  }

  /** These options with {@code delivery}. */
  public WatchOptions delivery(Delivery delivery) {
    return new WatchOptions(delivery, priority);
  }

  /** These options with {@code priority}. */
  public WatchOptions priority(Priority priority) {
    return new WatchOptions(delivery, priority);
  }

  /** How changes are delivered. */
  public Delivery delivery() {
    return delivery;
  }

  /** The priority of the watch's callbacks on the dispatcher. */
  public Priority priority() {
    return priority;
  }

  @Override
  public boolean equals(Object o) {
    return o instanceof WatchOptions w && w.delivery == delivery && w.priority == priority;
  }

  @Override
  public int hashCode() {
    return delivery.hashCode() * 31 + priority.hashCode();
  }

  @Override
  public String toString() {
    return "WatchOptions(" + delivery + ", " + priority + ")";
  }
}
