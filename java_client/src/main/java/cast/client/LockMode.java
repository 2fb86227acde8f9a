package cast.client;

/** What a lock keeps other components from doing (docs/design.md section 4). */
public enum LockMode {
  /** Others may not overwrite. */
  O,
  /** Others may neither overwrite nor delete (the default). */
  OD,
  /** Others may neither overwrite, delete nor read. */
  ODR
}
