package cast.client;

/** What a lock keeps other components from doing (docs/design.md section 4). */
public enum LockMode {
  /** Others may not overwrite. */
  O(cast.v1.LockMode.LOCK_MODE_O),
  /** Others may neither overwrite nor delete (the default). */
  OD(cast.v1.LockMode.LOCK_MODE_OD),
  /** Others may neither overwrite, delete nor read. */
  ODR(cast.v1.LockMode.LOCK_MODE_ODR);

  private final cast.v1.LockMode wire;

  LockMode(cast.v1.LockMode wire) {
    this.wire = wire;
  }

  /** The wire value. */
  public cast.v1.LockMode toProto() {
    return wire;
  }
}
