package cast.client;

import java.time.Duration;

/**
 * Where and as whom {@link Cast#connect(ConnectOptions)} connects. Every option is
 * optional; one left unset is looked up (docs/client-protocol.md, "Scripts"):
 *
 * <ul>
 *   <li>endpoint: {@code $CAST_ENDPOINT}, else "endpoint" of {@code <runtime dir>/system.json};
 *   <li>token: the file {@code $CAST_TOKEN_FILE}, {@code $CAST_TOKEN}, else one minted from the
 *       system's secret ({@code $CAST_SECRET}, the file {@code $CAST_SECRET_FILE},
 *       {@code <runtime dir>/secret}) for componentId (default {@code script-<host>-<pid>}) in
 *       subarchitecture (default: the first SA of the first server in system.json), privileged;
 *   <li>TLS: {@code $CAST_TLS_*}, else the "tls" block of system.json; else plaintext;
 *   <li>runtime dir: {@code $CAST_RUNTIME_DIR}, else {@code .cast}.
 * </ul>
 *
 * <pre>Cast.connect(new ConnectOptions().subarchitecture("vision"))</pre>
 */
public final class ConnectOptions {
  private String endpoint;
  private String token;
  private String componentId;
  private String subarchitecture;
  private String runtimeDir;
  private ClientTls tls;
  private Duration callTimeout = GrpcTransport.DEFAULT_CALL_TIMEOUT;

  /** No option set: everything is looked up. */
  public ConnectOptions() {}

  /** The system's directory, host:port. */
  public ConnectOptions endpoint(String endpoint) {
    this.endpoint = endpoint;
    return this;
  }

  /** A token from {@code cast token}; it decides the identity. */
  public ConnectOptions token(String token) {
    this.token = token;
    return this;
  }

  /** The component id of a minted token. */
  public ConnectOptions componentId(String componentId) {
    this.componentId = componentId;
    return this;
  }

  /** The own SA of a minted token (where calls go when they name no SA). */
  public ConnectOptions subarchitecture(String subarchitecture) {
    this.subarchitecture = subarchitecture;
    return this;
  }

  /** Where {@code cast run} keeps system.json and secret. */
  public ConnectOptions runtimeDir(String runtimeDir) {
    this.runtimeDir = runtimeDir;
    return this;
  }

  /** TLS files: the CA, optionally the client's certificate and key, and the server name. */
  public ConnectOptions tls(ClientTls tls) {
    this.tls = tls;
    return this;
  }

  /** Bounds every unary call except blocking locks (default 30 s). */
  public ConnectOptions callTimeout(Duration callTimeout) {
    if (callTimeout == null || callTimeout.isNegative() || callTimeout.isZero()) {
      throw new InvalidArgumentError("callTimeout must be positive, got " + callTimeout);
    }
    this.callTimeout = callTimeout;
    return this;
  }

  /** The endpoint given, or null. */
  public String endpoint() {
    return endpoint;
  }

  /** The token given, or null. */
  public String token() {
    return token;
  }

  /** The component id given, or null. */
  public String componentId() {
    return componentId;
  }

  /** The subarchitecture given, or null. */
  public String subarchitecture() {
    return subarchitecture;
  }

  /** The runtime directory given, or null. */
  public String runtimeDir() {
    return runtimeDir;
  }

  /** The TLS settings given, or null. */
  public ClientTls tls() {
    return tls;
  }

  /** The call timeout. */
  public Duration callTimeout() {
    return callTimeout;
  }
}
