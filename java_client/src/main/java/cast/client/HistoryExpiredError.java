package cast.client;

/** A watch fell behind (or asked for) revisions older than the server keeps: read the current state, then watch again (OUT_OF_RANGE). */
public class HistoryExpiredError extends CastError {
  private static final long serialVersionUID = 1L;

  /** The error with the server's (or the library's) message. */
  public HistoryExpiredError(String message) {
    super("OUT_OF_RANGE", message);
  }
}
