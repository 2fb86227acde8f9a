package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import java.nio.file.Files;
import java.nio.file.Path;
import java.util.HashMap;
import java.util.List;
import java.util.Map;
import org.junit.jupiter.api.Test;
import org.junit.jupiter.api.io.TempDir;

class ArgsAndContractTest {
  static Map<String, String> env(String args) {
    Map<String, String> env = new HashMap<>();
    env.put("CAST_ENDPOINT", "127.0.0.1:5");
    env.put("CAST_COMPONENT_ID", "c1");
    env.put("CAST_SUBARCHITECTURE", "vision");
    env.put("CAST_TOKEN", "tok.sig");
    if (args != null) {
      env.put("CAST_ARGS", args);
    }
    return env;
  }

  @Test
  void typedGettersReadJsonArguments() {
    Args a = Args.fromJson("{\"rate_hz\": 20, \"name\": \"s\u00e9g\", \"on\": true, \"gain\": 0.5, \"xs\": [1, \"b\"], \"sub\": {\"k\": 3}}");
    assertEquals(20, a.getInt("rate_hz", 0));
    assertEquals(20L, a.getLong("rate_hz", 0));
    assertEquals("s\u00e9g", a.getString("name", ""));
    assertTrue(a.getBoolean("on", false));
    assertEquals(0.5, a.getDouble("gain", 0));
    assertEquals(List.of(1.0, "b"), a.getList("xs"));
    assertEquals(3, a.getObject("sub").getInt("k", 0));
    assertEquals("dflt", a.getString("absent", "dflt"));
    assertEquals(7, a.getInt("absent", 7));
    assertTrue(a.has("name"));
    assertFalse(a.has("absent"));
  }

  @Test
  void aWrongTypeNamesTheArgument() {
    Args a = Args.fromJson("{\"rate_hz\": \"fast\", \"n\": 1.5}");
    InvalidArgumentError e = assertThrows(InvalidArgumentError.class, () -> a.getInt("rate_hz", 0));
    assertTrue(e.getMessage().contains("'rate_hz'") && e.getMessage().contains("a string"), e.getMessage());
    assertThrows(InvalidArgumentError.class, () -> a.getLong("n", 0));
  }

  @Test
  void argsMustBeAJsonObject() {
    assertThrows(InvalidArgumentError.class, () -> Args.fromJson("[1,2]"));
    assertThrows(InvalidArgumentError.class, () -> Args.fromJson("{bad json"));
    assertTrue(Args.fromJson("").names().isEmpty());
    assertTrue(Args.fromJson(null).names().isEmpty());
  }

  @Test
  void contractReadsTheEnvironment() {
    LaunchContract c = LaunchContract.fromEnv(env("{\"a\": 1}"));
    assertEquals("127.0.0.1:5", c.endpoint());
    assertEquals("c1", c.componentId());
    assertEquals("vision", c.subarchitecture());
    assertEquals("tok.sig", c.token());
    assertEquals(1, c.args().getInt("a", 0));
    assertFalse(c.toString().contains("tok.sig"), "the token must not be printed");
    assertTrue(LaunchContract.fromEnv(env(null)).args().names().isEmpty(), "CAST_ARGS is optional");
  }

  @Test
  void missingVariablesAreAllNamed() {
    Map<String, String> e = env("{}");
    e.remove("CAST_TOKEN");
    e.put("CAST_ENDPOINT", "");
    InvalidArgumentError err = assertThrows(InvalidArgumentError.class, () -> LaunchContract.fromEnv(e));
    assertTrue(
        err.getMessage().startsWith("missing launch environment: CAST_ENDPOINT, CAST_TOKEN or CAST_TOKEN_FILE; start"),
        err.getMessage());
    InvalidArgumentError bad = assertThrows(InvalidArgumentError.class, () -> LaunchContract.fromEnv(env("[]")));
    assertTrue(bad.getMessage().startsWith("CAST_ARGS"), bad.getMessage());
  }

  /**
   * The file is the renewed token: set, it is the token (CAST_TOKEN may be absent, as in an exported pod),
   * and it wins over CAST_TOKEN, as for Cast.connect (ConnectResolverTest). Empty or unreadable, it is
   * named, not passed over. A real runner: tests/interop/test_java_runner.py.
   */
  @Test
  void theTokenFileIsTheTokenWhenSet(@TempDir Path dir) throws Exception {
    Path file = dir.resolve("c1.token");
    Files.writeString(file, "\n  file.token \n");
    Map<String, String> e = env("{}");
    e.remove("CAST_TOKEN");
    e.put("CAST_TOKEN_FILE", file.toString());
    LaunchContract c = LaunchContract.fromEnv(e);
    assertEquals("file.token", c.token());
    assertEquals(file.toString(), c.tokenFile());
    e.put("CAST_TOKEN", "stale.token");
    assertEquals("file.token", LaunchContract.fromEnv(e).token());
    Files.writeString(file, " \n");
    InvalidArgumentError empty = assertThrows(InvalidArgumentError.class, () -> LaunchContract.fromEnv(e));
    assertEquals(
        "CAST_TOKEN_FILE names " + file + ", which is empty: point it at a token file (`cast run` renews one per"
            + " component), or unset it",
        empty.getMessage());
    Files.delete(file);
    InvalidArgumentError gone = assertThrows(InvalidArgumentError.class, () -> LaunchContract.fromEnv(e));
    assertTrue(gone.getMessage().startsWith("CAST_TOKEN_FILE names " + file + ", which cannot be read"), gone.getMessage());
  }
}
