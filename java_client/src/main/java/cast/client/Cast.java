package cast.client;

import java.time.Instant;

/** Entry points of the library for plain programs: {@link #connect()}. */
public final class Cast {
  private Cast() {}

  /**
   * Connects to the running system found from the environment and the runtime
   * directory (see {@link ConnectOptions} for the order); the twin of Python's
   * {@code cast.connect()} and C++'s {@code cast::connect()}.
   */
  public static Connection connect() {
    return connect(new ConnectOptions());
  }

  /**
   * Connects as {@code options} say, looking up what they leave unset. NotFoundError
   * saying what to give when no system or token can be found (InvalidArgumentError for
   * a missing subarchitecture, or options that contradict whom the server says the token
   * was issued to), UnavailableError when nothing answers at the endpoint,
   * UnauthenticatedError when the token is refused (not a CAST token, expired, forged).
   */
  public static Connection connect(ConnectOptions options) {
    ConnectResolver.Resolved found =
        ConnectResolver.resolve(options, System.getenv(), Instant.now().getEpochSecond());
    LaunchContract contract = found.contract();
    GrpcTransport transport;
    try {
      transport =
          new GrpcTransport(
              contract, endpoint -> GrpcServer.channel(endpoint, contract.tls()), options.callTimeout());
    } catch (UnavailableError e) {
      // Say where the address came from: a stale system.json or CAST_ENDPOINT is the usual cause.
      throw new UnavailableError(
          "no CAST system answers at "
              + contract.endpoint()
              + " (from "
              + found.endpointSource()
              + (contract.tls() == null ? ", spoken to in plaintext" : ", spoken to with TLS")
              + "): "
              + e.getMessage());
    } catch (IllegalArgumentException e) { // an endpoint grpc cannot parse as host:port
      throw new InvalidArgumentError(
          "bad endpoint '" + contract.endpoint() + "' (from " + found.endpointSource() + "): " + e.getMessage());
    } catch (UnauthenticatedError e) { // a system whose reads need a token refused it already
      throw refused(found, e);
    }
    try {
      return new Connection(transport, found::verify);
    } catch (UnauthenticatedError e) {
      throw refused(found, e);
    } catch (RuntimeException e) {
      transport.close();
      throw e;
    }
  }

  /** The server's refusal of the token, saying where the token came from and how to get one. */
  private static UnauthenticatedError refused(ConnectResolver.Resolved found, UnauthenticatedError e) {
    return new UnauthenticatedError(
        "the server refused the token from "
            + found.tokenSource()
            + ": "
            + e.getMessage()
            + " (`cast token COMPONENT_ID --sa SA` prints one)");
  }
}
