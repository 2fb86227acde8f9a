package cast.client;

import static cast.client.ConnectResolver.given;

import java.util.ArrayList;
import java.util.List;
import java.util.Map;

/**
 * The environment a component process is started with (docs/design.md section 6):
 * CAST_ENDPOINT, CAST_COMPONENT_ID, CAST_SUBARCHITECTURE, the token and CAST_ARGS
 * (a JSON object); CAST_START_BARRIER=1 when {@code cast run} launched it. The token
 * is the content of the file CAST_TOKEN_FILE names when that is set (re-read when
 * renewed), else CAST_TOKEN.
 *
 * @param endpoint the directory's address, host:port
 * @param componentId this component's id; the server's answer to Register must agree
 *     (null: any, as for a script connecting with a token)
 * @param subarchitecture this component's SA; the server's answer must agree (null: any)
 * @param token the signed token the orchestrator (or {@code cast token}) issued, as first read
 * @param args the component's arguments
 * @param tls TLS settings (CAST_TLS_*), or null for plaintext
 * @param tokenFile CAST_TOKEN_FILE, the file the orchestrator renews the token in, or null
 * @param startBarrier CAST_START_BARRIER=1: run() waits until every component of the system
 *     has finished start() (docs/client-protocol.md, "Start-up")
 */
public record LaunchContract(
    String endpoint,
    String componentId,
    String subarchitecture,
    String token,
    Args args,
    ClientTls tls,
    String tokenFile,
    boolean startBarrier) {

  /** A contract without the start barrier (a component not launched by {@code cast run}). */
  public LaunchContract(
      String endpoint, String componentId, String subarchitecture, String token, Args args, ClientTls tls,
      String tokenFile) {
    this(endpoint, componentId, subarchitecture, token, args, tls, tokenFile, false);
  }

  /** A plaintext contract with a fixed token. */
  public LaunchContract(String endpoint, String componentId, String subarchitecture, String token, Args args) {
    this(endpoint, componentId, subarchitecture, token, args, null, null, false);
  }

  /** The variables that must be set, besides the token (CAST_TOKEN or CAST_TOKEN_FILE). */
  public static final List<String> REQUIRED =
      List.of("CAST_ENDPOINT", "CAST_COMPONENT_ID", "CAST_SUBARCHITECTURE");

  /**
   * Read the contract from {@code env}; InvalidArgumentError naming every missing variable. The token is
   * the file CAST_TOKEN_FILE names when that is set (the renewed one, so it wins over CAST_TOKEN, as for
   * {@link Cast#connect}); an empty or unreadable file is an error, not a fallback.
   */
  public static LaunchContract fromEnv(Map<String, String> env) {
    List<String> missing = new ArrayList<>();
    for (String name : REQUIRED) {
      if (!given(env.get(name))) {
        missing.add(name);
      }
    }
    if (!given(env.get("CAST_TOKEN")) && !given(env.get("CAST_TOKEN_FILE"))) {
      missing.add("CAST_TOKEN or CAST_TOKEN_FILE");
    }
    if (!missing.isEmpty()) {
      throw new InvalidArgumentError(
          "missing launch environment: "
              + String.join(", ", missing)
              + "; start the component with `cast run CONFIG`, or get the variables from `cast token`");
    }
    Args args;
    try {
      args = Args.fromJson(env.get("CAST_ARGS"));
    } catch (InvalidArgumentError e) {
      throw new InvalidArgumentError("CAST_ARGS: " + e.getMessage());
    }
    String tokenFile = given(env.get("CAST_TOKEN_FILE")) ? env.get("CAST_TOKEN_FILE") : null;
    return new LaunchContract(
        env.get("CAST_ENDPOINT"),
        env.get("CAST_COMPONENT_ID"),
        env.get("CAST_SUBARCHITECTURE"),
        tokenFile != null ? ConnectResolver.readTokenFile(tokenFile) : env.get("CAST_TOKEN"),
        args,
        ClientTls.fromEnv(env),
        tokenFile,
        "1".equals(env.get("CAST_START_BARRIER")));
  }

  /** Read the contract from the process environment. */
  public static LaunchContract fromEnv() {
    return fromEnv(System.getenv());
  }

  @Override
  public String toString() {
    // Never print the token: logs are read by people who should not hold it.
    return "LaunchContract("
        + (componentId == null ? "<the token's id>" : componentId)
        + "@"
        + (subarchitecture == null ? "<the token's SA>" : subarchitecture)
        + " via "
        + endpoint
        + (tls == null ? "" : " (TLS)")
        + (startBarrier ? " (start barrier)" : "")
        + ", args="
        + args
        + ")";
  }
}
