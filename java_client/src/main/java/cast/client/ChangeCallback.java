package cast.client;

/** Receives the changes of an {@code onChange} registration, on the component's dispatcher thread. */
@FunctionalInterface
public interface ChangeCallback {
  /** Called once per matching change, in revision order; an exception is logged, not fatal. */
  void onChange(WorkingMemoryChange change) throws Exception;
}
