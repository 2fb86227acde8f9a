package cast.client;

/**
 * A held lock level; closing it unlocks (idempotent), so
 * {@code try (LockGuard g = lock(id)) { ... }} unlocks at the end of the block.
 */
public final class LockGuard implements AutoCloseable {
  private final Component component;
  private final WorkingMemoryAddress address;
  private final int depth;
  private boolean released; // guarded by this

  LockGuard(Component component, WorkingMemoryAddress address, int depth) {
    this.component = component;
    this.address = address;
    this.depth = depth;
  }

  /** The locked entry. */
  public WorkingMemoryAddress address() {
    return address;
  }

  /** How many times the component held the lock right after taking this level. */
  public int depth() {
    return depth;
  }

  /** Whether this level was released. */
  public synchronized boolean isReleased() {
    return released;
  }

  /** Release this lock level once; later calls do nothing. */
  public void unlock() {
    synchronized (this) {
      if (released) {
        return;
      }
      released = true;
    }
    component.unlock(address.id(), address.subarchitecture());
  }

  /** Same as {@link #unlock()}: for try-with-resources. */
  @Override
  public void close() {
    unlock();
  }

  @Override
  public String toString() {
    return "LockGuard(" + address + " depth=" + depth + (isReleased() ? ", released" : "") + ")";
  }
}
