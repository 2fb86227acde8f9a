package cast.client;

import com.google.gson.JsonArray;
import com.google.gson.JsonElement;
import com.google.gson.JsonObject;
import com.google.gson.JsonParser;
import java.io.IOException;
import java.nio.charset.StandardCharsets;
import java.nio.file.Files;
import java.nio.file.Path;
import java.util.Map;
import java.util.function.Supplier;

/**
 * How {@link Cast#connect(ConnectOptions)} finds the system, its token and TLS (see
 * {@link ConnectOptions}), apart from connecting, so that the rules can be tested
 * with an environment and a runtime directory of a test's own.
 */
final class ConnectResolver {
  private ConnectResolver() {}

  /**
   * What was found: the contract to connect with, and where the endpoint and the token
   * came from.
   *
   * @param contract endpoint, identity (of a given token: only what the options say,
   *     null otherwise), token (and the file it is renewed in), TLS
   * @param endpointSource where the endpoint came from, for error messages
   * @param tokenSource where the token came from ("a token minted from ..." for a minted one)
   */
  record Resolved(LaunchContract contract, String endpointSource, String tokenSource) {
    /**
     * A given token decides the identity: InvalidArgumentError naming both when the
     * componentId or subarchitecture option contradicts what the server verified from it.
     */
    void verify(Identity verified) {
      Session.requireVerified(
          verified,
          contract.componentId(),
          "ConnectOptions.componentId",
          contract.subarchitecture(),
          "ConnectOptions.subarchitecture",
          "the token from " + tokenSource + " decides the identity; drop the option, or give a token for it");
    }
  }

  /** What {@code <runtime dir>/system.json} says, when a running {@code cast run} wrote it. */
  private record Recorded(boolean usable, Path path, String why, String endpoint, String firstSa, ClientTls tls) {
    static Recorded unusable(Path path, String why) {
      return new Recorded(false, path, why, null, null, null);
    }
  }

  /**
   * Resolves {@code options} against {@code env} and the runtime directory; a minted
   * token is issued at {@code now} (seconds since the epoch). NotFoundError (no system,
   * no token or secret) or InvalidArgumentError (no SA for a minted token) saying what to
   * give. A given token is not decoded: the server says whom it was issued to
   * ({@link Resolved#verify}), and refuses one that is no CAST token.
   */
  static Resolved resolve(ConnectOptions options, Map<String, String> env, long now) {
    String dirName = firstOf(options.runtimeDir(), env.get("CAST_RUNTIME_DIR"), ".cast");
    Path dir = Path.of(dirName);
    // Read at most once, and only when an earlier source has nothing.
    Recorded[] cache = new Recorded[1];
    Supplier<Recorded> system =
        () -> {
          if (cache[0] == null) {
            cache[0] = readSystemJson(dir);
          }
          return cache[0];
        };

    String endpoint;
    String endpointSource;
    if (given(options.endpoint())) {
      endpoint = options.endpoint();
      endpointSource = "ConnectOptions.endpoint";
    } else if (given(env.get("CAST_ENDPOINT"))) {
      endpoint = env.get("CAST_ENDPOINT");
      endpointSource = "CAST_ENDPOINT";
    } else if (system.get().usable()) {
      endpoint = system.get().endpoint();
      endpointSource = system.get().path().toString();
    } else {
      throw new NotFoundError(
          "no CAST system to connect to: "
              + system.get().why()
              + "; start one with `cast run CONFIG`, give ConnectOptions.runtimeDir (or CAST_RUNTIME_DIR) where it"
              + " runs, or give ConnectOptions.endpoint (or CAST_ENDPOINT)");
    }

    String token = null;
    String tokenFile = null;
    String source = null;
    if (given(options.token())) {
      token = options.token();
      source = "ConnectOptions.token";
    } else if (given(env.get("CAST_TOKEN_FILE"))) {
      tokenFile = env.get("CAST_TOKEN_FILE");
      token = readTokenFile(tokenFile);
      source = "the file " + tokenFile + " (CAST_TOKEN_FILE)";
    } else if (given(env.get("CAST_TOKEN"))) {
      token = env.get("CAST_TOKEN");
      source = "CAST_TOKEN";
    }

    Identity identity;
    if (token != null) {
      // Who the token is for is the server's answer to Register; the options are checked against it.
      identity = new Identity(blankToNull(options.componentId()), blankToNull(options.subarchitecture()), false);
    } else {
      String[] secret = findSecret(env, dir);
      if (secret == null) {
        throw new NotFoundError(
            "no token and no secret to mint one: give ConnectOptions.token, set CAST_TOKEN or CAST_TOKEN_FILE"
                + " (`cast token` prints a token), or set CAST_SECRET or CAST_SECRET_FILE to the system's secret ("
                + dir.resolve("secret")
                + ", which a running `cast run` writes, does not exist)");
      }
      String sa = options.subarchitecture();
      if (!given(sa)) {
        Recorded r = system.get();
        if (!r.usable() || r.firstSa() == null) {
          throw new InvalidArgumentError(
              "which subarchitecture is this program's own? give ConnectOptions.subarchitecture ("
                  + (r.usable() ? r.path() + " lists no subarchitecture" : r.why())
                  + ", so it cannot be taken from there)");
        }
        sa = r.firstSa();
      }
      // Whoever holds the secret could mint any token: it is trusted.
      identity = new Identity(firstOf(options.componentId(), null, defaultScriptId()), sa, true);
      source = secret[1] + " (a token minted with the system's secret)";
      try {
        token = Tokens.mint(secret[0].getBytes(StandardCharsets.UTF_8), identity, now);
      } catch (InvalidArgumentError e) {
        throw new InvalidArgumentError("the secret from " + secret[1] + ": " + e.getMessage());
      }
    }

    ClientTls tls;
    if (options.tls() != null) {
      ClientTls t = options.tls();
      if (!given(t.ca())) {
        throw new InvalidArgumentError(
            "ConnectOptions.tls has no ca: give the PEM file of the CA that signed the servers' certificates"
                + " (or no tls, for plaintext)");
      }
      if (given(t.cert()) != given(t.key())) {
        throw new InvalidArgumentError("ConnectOptions.tls: give both cert and key, or neither");
      }
      tls = new ClientTls(t.ca(), given(t.cert()) ? t.cert() : null, given(t.key()) ? t.key() : null,
          t.serverName() == null ? "" : t.serverName());
    } else {
      tls = ClientTls.fromEnv(env);
      if (tls == null && system.get().usable()) {
        tls = system.get().tls();
      }
    }
    LaunchContract contract =
        new LaunchContract(
            endpoint, identity.componentId(), identity.subarchitecture(), token, Args.empty(), tls, tokenFile);
    return new Resolved(contract, endpointSource, source);
  }

  /** The component id of a minted token when none is given: script-&lt;host&gt;-&lt;pid&gt;. */
  static String defaultScriptId() {
    String host = Session.hostName();
    return "script-" + (host.isEmpty() ? "localhost" : host) + "-" + ProcessHandle.current().pid();
  }

  /** Whether an environment variable or option is set and not empty (the launch contract's test too). */
  static boolean given(String s) {
    return s != null && !s.isEmpty();
  }

  private static String blankToNull(String s) {
    return given(s) ? s : null;
  }

  private static String firstOf(String a, String b, String otherwise) {
    return given(a) ? a : given(b) ? b : otherwise;
  }

  /**
   * The token in the file CAST_TOKEN_FILE names, trimmed; InvalidArgumentError naming the variable and
   * the path if it is empty or cannot be read. The file is the renewed token, so when it is set it is the
   * token, not CAST_TOKEN: here and in the runner's {@link LaunchContract} alike (and in C++ and Python).
   */
  static String readTokenFile(String path) {
    return readTrimmed(Path.of(path), "CAST_TOKEN_FILE", "a token file (`cast run` renews one per component)");
  }

  /** A file's text, trimmed; InvalidArgumentError naming the variable that named it. */
  private static String readTrimmed(Path path, String variable, String what) {
    String text;
    try {
      text = Files.readString(path, StandardCharsets.UTF_8).strip();
    } catch (IOException e) {
      throw new InvalidArgumentError(
          variable + " names " + path + ", which cannot be read: point it at " + what + ", or unset it");
    }
    if (text.isEmpty()) {
      throw new InvalidArgumentError(variable + " names " + path + ", which is empty: point it at " + what + ", or unset it");
    }
    return text;
  }

  /** The system's secret and where it came from, or null. */
  private static String[] findSecret(Map<String, String> env, Path dir) {
    if (given(env.get("CAST_SECRET"))) {
      return new String[] {env.get("CAST_SECRET"), "CAST_SECRET"};
    }
    if (given(env.get("CAST_SECRET_FILE"))) {
      Path path = Path.of(env.get("CAST_SECRET_FILE"));
      return new String[] {
        readTrimmed(path, "CAST_SECRET_FILE", "the system's secret file"), "the file " + path + " (CAST_SECRET_FILE)"
      };
    }
    Path path = dir.resolve("secret");
    try {
      String text = Files.readString(path, StandardCharsets.UTF_8).strip();
      return text.isEmpty() ? null : new String[] {text, path.toString()};
    } catch (IOException e) {
      return null;
    }
  }

  private static Recorded readSystemJson(Path dir) {
    Path path = dir.resolve("system.json");
    JsonObject state;
    try {
      state = JsonParser.parseString(Files.readString(path, StandardCharsets.UTF_8)).getAsJsonObject();
    } catch (IOException e) {
      return Recorded.unusable(path, "there is no " + path + " (a running `cast run` writes it)");
    } catch (RuntimeException e) {
      return Recorded.unusable(path, path + " is not a JSON object (" + e.getMessage() + ")");
    }
    JsonElement pid = state.get("pid");
    if (pid == null || !pid.isJsonPrimitive() || !pid.getAsJsonPrimitive().isNumber()) {
      return Recorded.unusable(path, path + " names no process (\"pid\"), so it was not written by `cast run`");
    }
    // A `cast run` that was killed leaves its system.json behind.
    long number = pid.getAsLong();
    if (number <= 0 || !ProcessHandle.of(number).map(ProcessHandle::isAlive).orElse(false)) {
      return Recorded.unusable(path, path + " was written by process " + number + ", which is no longer running");
    }
    String endpoint = string(state, "endpoint");
    if (endpoint == null) {
      return Recorded.unusable(path, path + " has no \"endpoint\"");
    }
    String firstSa = null;
    JsonElement servers = state.get("servers");
    if (servers != null && servers.isJsonObject() && servers.getAsJsonObject().size() > 0) {
      // Gson keeps the members in the file's order: the first is the first server `cast run` wrote.
      JsonElement first = servers.getAsJsonObject().entrySet().iterator().next().getValue();
      JsonElement sas = first.isJsonObject() ? first.getAsJsonObject().get("subarchitectures") : null;
      if (sas != null && sas.isJsonArray() && ((JsonArray) sas).size() > 0) {
        JsonElement sa = ((JsonArray) sas).get(0);
        firstSa = sa.isJsonPrimitive() ? sa.getAsString() : null;
      }
    }
    ClientTls tls = null;
    JsonElement t = state.get("tls");
    if (t != null && t.isJsonObject() && string(t.getAsJsonObject(), "ca") != null) {
      JsonObject o = t.getAsJsonObject();
      tls = new ClientTls(string(o, "ca"), string(o, "cert"), string(o, "key"), "");
    }
    return new Recorded(true, path, null, endpoint, firstSa, tls);
  }

  /** A non-empty string member, or null. */
  private static String string(JsonObject o, String key) {
    JsonElement e = o.get(key);
    return e != null && e.isJsonPrimitive() && e.getAsJsonPrimitive().isString() && !e.getAsString().isEmpty()
        ? e.getAsString()
        : null;
  }
}
