package cast.client;

/**
 * What an {@code onChange} watch receives when its component falls behind the writers
 * (docs/client-protocol.md, "Watching"); set with {@link WatchOptions}.
 */
public enum Delivery {
  /** Every change, in revision order (the default). */
  QUEUE,
  /**
   * Only the newest change of each entry not yet delivered: the server and the client replace
   * an undelivered change of an entry by the newer one, and {@link WorkingMemoryChange#skipped()}
   * says how many it replaced. For fast data (images, poses) read by slower callbacks.
   */
  LATEST
}
