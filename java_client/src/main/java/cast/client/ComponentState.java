package cast.client;

/** A component's life stage as its session reports it (what {@code cast components} shows). */
enum ComponentState {
  /** Registered; configure and start are running. */
  STARTING,
  /** start() returned, its watches are registered: run() waits for the start barrier (under {@code cast run}). */
  STARTED,
  /** run() is running (a Connection: from the start, nothing else will run). */
  RUNNING,
  /** stop() was called. */
  STOPPING
}
