package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import java.io.IOException;
import java.nio.charset.StandardCharsets;
import java.nio.file.Files;
import java.nio.file.Path;
import java.util.Base64;
import java.util.HashMap;
import java.util.Map;
import org.junit.jupiter.api.Test;
import org.junit.jupiter.api.io.TempDir;

/** How Cast.connect finds the endpoint, token and TLS: environment, runtime directory, minting. */
class ConnectResolverTest {
  static final String SECRET = "test-secret-0123456789abcdef-0123456789";

  @TempDir Path dir;

  /** A system.json as a running `cast run` writes it (its pid: this JVM, alive, unless given). */
  void system(String extra, long pid) throws IOException {
    Files.writeString(
        dir.resolve("system.json"),
        "{\"system\": \"test\", \"endpoint\": \"127.0.0.1:7001\",\n"
            + " \"servers\": {\"zeta\": {\"endpoint\": \"127.0.0.1:7001\", \"subarchitectures\": [\"motor\", \"vision\"]},\n"
            + "             \"alpha\": {\"endpoint\": \"127.0.0.1:7002\", \"subarchitectures\": [\"language\"]}},\n"
            + " \"pid\": "
            + pid
            + ", \"config\": \"system.yaml\""
            + extra
            + "}");
  }

  void system() throws IOException {
    system("", ProcessHandle.current().pid());
  }

  ConnectOptions inDir() {
    return new ConnectOptions().runtimeDir(dir.toString());
  }

  static String errorOf(ConnectOptions options, Map<String, String> env) {
    return errorOf(InvalidArgumentError.class, options, env);
  }

  /** The message of the error {@code type} that resolving throws (another error fails the test). */
  static String errorOf(Class<? extends CastError> type, ConnectOptions options, Map<String, String> env) {
    return assertThrows(type, () -> ConnectResolver.resolve(options, env, 0)).getMessage();
  }

  static LaunchContract resolve(ConnectOptions options, Map<String, String> env, long now) {
    return ConnectResolver.resolve(options, env, now).contract();
  }

  // ---------------------------------------------------------------- the endpoint

  @Test
  void endpointFromTheOptionThenTheEnvironmentThenSystemJson() throws IOException {
    system();
    ConnectOptions options = inDir().token(TokensTest.PLANNER_TOKEN);
    assertEquals("127.0.0.1:7001", resolve(options, Map.of(), 0).endpoint());
    assertEquals(dir.resolve("system.json").toString(), ConnectResolver.resolve(options, Map.of(), 0).endpointSource());
    assertEquals("env:1", resolve(options, Map.of("CAST_ENDPOINT", "env:1"), 0).endpoint());
    assertEquals("option:2", resolve(options.endpoint("option:2"), Map.of("CAST_ENDPOINT", "env:1"), 0).endpoint());
  }

  @Test
  void theRuntimeDirComesFromTheEnvironmentToo() throws IOException {
    system();
    ConnectOptions options = new ConnectOptions().token(TokensTest.PLANNER_TOKEN);
    assertEquals("127.0.0.1:7001", resolve(options, Map.of("CAST_RUNTIME_DIR", dir.toString()), 0).endpoint());
  }

  @Test
  void noSystemSaysWhatToGive() {
    String message = errorOf(NotFoundError.class, inDir(), Map.of());
    assertTrue(message.startsWith("no CAST system to connect to: there is no " + dir.resolve("system.json")), message);
    assertTrue(message.contains("`cast run CONFIG`"), message);
    assertTrue(message.contains("ConnectOptions.endpoint (or CAST_ENDPOINT)"), message);
  }

  @Test
  void systemJsonOfAProcessThatIsGoneIsIgnored() throws IOException {
    system("", 999_999_999L); // above any pid_max
    String message = errorOf(NotFoundError.class, inDir(), Map.of());
    assertTrue(message.contains("was written by process 999999999, which is no longer running"), message);
  }

  // ---------------------------------------------------------------- given tokens

  @Test
  void tokenFromTheOptionThenTheTokenFileThenTheEnvironment() throws IOException {
    system();
    Path file = dir.resolve("worker.token");
    Files.writeString(file, TokensTest.WORKER_TOKEN + "\n");
    Map<String, String> env = new HashMap<>(Map.of("CAST_TOKEN_FILE", file.toString(), "CAST_TOKEN", TokensTest.PLANNER_TOKEN));

    ConnectResolver.Resolved found = ConnectResolver.resolve(inDir(), env, 0);
    LaunchContract c = found.contract();
    assertEquals(TokensTest.WORKER_TOKEN, c.token());
    assertEquals(file.toString(), c.tokenFile()); // renewed tokens are picked up from there
    assertEquals("the file " + file + " (CAST_TOKEN_FILE)", found.tokenSource());
    // A given token is not decoded: whom it is for is the server's answer to Register.
    assertNull(c.componentId());
    assertNull(c.subarchitecture());

    env.remove("CAST_TOKEN_FILE");
    found = ConnectResolver.resolve(inDir(), env, 0);
    assertEquals(TokensTest.PLANNER_TOKEN, found.contract().token());
    assertNull(found.contract().tokenFile());
    assertEquals("CAST_TOKEN", found.tokenSource());

    found = ConnectResolver.resolve(inDir().token(TokensTest.WORKER_TOKEN).componentId("worker"), env, 0);
    assertEquals(TokensTest.WORKER_TOKEN, found.contract().token());
    assertEquals("ConnectOptions.token", found.tokenSource());
    // The options stay, to be checked against the server's answer (IdentityTest).
    assertEquals("worker", found.contract().componentId());
    assertNull(found.contract().subarchitecture());
  }

  @Test
  void aTokenFileThatCannotBeReadIsNamed() throws IOException {
    system();
    Path none = dir.resolve("none");
    assertTrue(
        errorOf(inDir(), Map.of("CAST_TOKEN_FILE", none.toString()))
            .startsWith("CAST_TOKEN_FILE names " + none + ", which cannot be read"));
    Path empty = dir.resolve("empty");
    Files.writeString(empty, "\n");
    assertTrue(
        errorOf(inDir(), Map.of("CAST_TOKEN_FILE", empty.toString())).startsWith("CAST_TOKEN_FILE names " + empty + ", which is empty"));
    // A token that is no CAST token, or one for another identity than the options say, is the
    // server's to refuse: tests/interop/test_java_identity.py and IdentityTest.
  }

  // ---------------------------------------------------------------- minted tokens

  @Test
  void mintsAPrivilegedTokenFromTheRuntimeDirsSecret() throws IOException {
    system();
    Files.writeString(dir.resolve("secret"), SECRET + "\n");
    LaunchContract c = resolve(inDir(), Map.of(), 1_700_000_123L);
    assertEquals(
        "script-" + Session.hostName() + "-" + ProcessHandle.current().pid(), c.componentId());
    assertEquals("motor", c.subarchitecture()); // the first SA of the first server, in the file's order
    // The token verifies with the secret: its signature is HS256 over header.payload.
    String[] parts = c.token().split("\\.");
    assertEquals(3, parts.length);
    assertEquals(Tokens.HEADER, parts[0]);
    assertEquals(Tokens.signHs256(parts[0] + "." + parts[1], SECRET.getBytes(StandardCharsets.UTF_8)), parts[2]);
    assertEquals(
        "{\"c\":\"" + c.componentId() + "\",\"s\":\"motor\",\"p\":true,\"iat\":1700000123}",
        new String(Base64.getUrlDecoder().decode(parts[1]), StandardCharsets.UTF_8));
    assertNull(c.tokenFile());
  }

  @Test
  void theSecretComesFromTheEnvironmentFirst() throws IOException {
    system();
    Files.writeString(dir.resolve("secret"), "the-runtime-dirs-secret-is-not-used-here");
    ConnectOptions options = inDir().componentId("notebook").subarchitecture("language");
    String other = "another-secret-0123456789abcdef-0123456789";
    Path file = dir.resolve("other.secret");
    Files.writeString(file, "  " + other + "\n");

    LaunchContract c = resolve(options, Map.of("CAST_SECRET", SECRET, "CAST_SECRET_FILE", file.toString()), 5);
    Identity notebook = new Identity("notebook", "language", true);
    assertEquals(Tokens.mint(SECRET.getBytes(StandardCharsets.UTF_8), notebook, 5), c.token());
    c = resolve(options, Map.of("CAST_SECRET_FILE", file.toString()), 5);
    assertEquals(Tokens.mint(other.getBytes(StandardCharsets.UTF_8), notebook, 5), c.token());
    assertEquals("notebook", c.componentId());
  }

  @Test
  void mintingNeedsASubarchitectureAndASecret() {
    ConnectOptions options = inDir().endpoint("127.0.0.1:7001");
    String noSecret = errorOf(NotFoundError.class, options, Map.of());
    assertTrue(noSecret.startsWith("no token and no secret to mint one: give ConnectOptions.token"), noSecret);
    assertTrue(noSecret.contains(dir.resolve("secret").toString()), noSecret);

    String noSa = errorOf(options, Map.of("CAST_SECRET", SECRET));
    assertTrue(noSa.contains("give ConnectOptions.subarchitecture"), noSa);

    String shortSecret = errorOf(options.subarchitecture("vision"), Map.of("CAST_SECRET", "abc"));
    assertTrue(shortSecret.startsWith("the secret from CAST_SECRET: the token secret is 3 bytes"), shortSecret);
  }

  // ---------------------------------------------------------------- TLS

  @Test
  void tlsFromTheOptionThenTheEnvironmentThenSystemJson() throws IOException {
    system(", \"tls\": {\"ca\": \"/pki/ca.pem\", \"cert\": \"/pki/client.pem\", \"key\": \"/pki/client.key\"}",
        ProcessHandle.current().pid());
    ConnectOptions options = inDir().token(TokensTest.PLANNER_TOKEN);
    assertEquals(
        new ClientTls("/pki/ca.pem", "/pki/client.pem", "/pki/client.key", ""), resolve(options, Map.of(), 0).tls());
    assertEquals(
        new ClientTls("env-ca.pem", null, null, "wm"),
        resolve(options, Map.of("CAST_TLS_CA", "env-ca.pem", "CAST_TLS_SERVER_NAME", "wm"), 0).tls());
    options.tls(new ClientTls("option-ca.pem", null, null, ""));
    assertEquals("option-ca.pem", resolve(options, Map.of("CAST_TLS_CA", "env-ca.pem"), 0).tls().ca());
    options.tls(new ClientTls("option-ca.pem", "client.pem", null, ""));
    assertTrue(errorOf(options, Map.of()).contains("give both cert and key"));

    system(", \"tls\": null", ProcessHandle.current().pid());
    assertNull(resolve(options.tls(null), Map.of(), 0).tls());
  }
}
