package cast.client;

/** The kind of a write, as seen in change events and used in filters. */
public enum Operation {
  /** An entry was created. */
  ADD,
  /** An entry's value was replaced. */
  OVERWRITE,
  /** An entry was removed. */
  DELETE
}
