package cast.client;

/** The kind of a write, as seen in change events and used in filters. */
public enum Operation {
  /** An entry was created. */
  ADD(cast.v1.Operation.OPERATION_ADD),
  /** An entry's value was replaced. */
  OVERWRITE(cast.v1.Operation.OPERATION_OVERWRITE),
  /** An entry was removed. */
  DELETE(cast.v1.Operation.OPERATION_DELETE);

  private final cast.v1.Operation wire;

  Operation(cast.v1.Operation wire) {
    this.wire = wire;
  }

  /** The wire value. */
  public cast.v1.Operation toProto() {
    return wire;
  }

  /** The operation of a wire value; InvalidArgumentError for UNSPECIFIED or unknown values. */
  public static Operation fromProto(cast.v1.Operation op) {
    for (Operation o : values()) {
      if (o.wire == op) {
        return o;
      }
    }
    throw new InvalidArgumentError("unknown operation " + op + " in a change event");
  }
}
