package cast.client;

/**
 * Which of a component's pending callbacks its dispatcher runs first: every pending callback
 * of a higher priority before any of a lower one, in arrival order within one priority (so
 * one watch's changes stay in order). Set per watch with {@link WatchOptions}; hooks
 * (task decisions, {@code watchFailed}) run at {@link #MEDIUM}.
 */
public enum Priority {
  /** Before every MEDIUM and LOW callback. */
  HIGH,
  /** The default. */
  MEDIUM,
  /** After every HIGH and MEDIUM callback. */
  LOW
}
