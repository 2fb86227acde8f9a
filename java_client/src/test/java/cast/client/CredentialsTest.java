package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import java.nio.file.Files;
import java.nio.file.Path;
import java.util.Map;
import org.junit.jupiter.api.Test;
import org.junit.jupiter.api.io.TempDir;

/** The token a call carries (fixed, or renewed through its file) and the TLS settings. */
class CredentialsTest {
  @TempDir Path dir;

  @Test
  void aFixedTokenNeverChanges() {
    Credentials t = new Credentials("fixed", null);
    assertEquals("fixed", t.token());
    assertFalse(t.refresh());
  }

  @Test
  void theFileWinsOverTheEnvironmentAndIsReReadWhenItChanges() throws Exception {
    Path file = dir.resolve("token");
    Files.writeString(file, "from-file\n");
    Credentials t = new Credentials("from-env", file, 60_000_000_000L);
    assertEquals("from-file", t.token());
    Files.writeString(file, "renewed-and-longer");
    assertEquals("from-file", t.token(), "checked at most once per interval");
    assertTrue(t.refresh(), "a refused call re-reads at once");
    assertEquals("renewed-and-longer", t.token());
    assertFalse(t.refresh(), "unchanged");
  }

  @Test
  void anEmptyOrMissingFileKeepsTheLastToken() throws Exception {
    Path file = dir.resolve("token");
    Files.writeString(file, "first");
    Credentials t = new Credentials("env", file, 0);
    assertEquals("first", t.token());
    Files.writeString(file, "");
    assertEquals("first", t.token());
    Files.delete(file);
    assertEquals("first", t.token());
    assertEquals("env", new Credentials("env", dir.resolve("missing"), 0).token());
  }

  @Test
  void tlsSettingsComeFromTheEnvironment() {
    assertNull(ClientTls.fromEnv(Map.of()));
    ClientTls tls = ClientTls.fromEnv(Map.of("CAST_TLS_CA", "ca.pem", "CAST_TLS_SERVER_NAME", "cast.local"));
    assertEquals(new ClientTls("ca.pem", null, null, "cast.local"), tls);
    InvalidArgumentError noCa =
        assertThrows(InvalidArgumentError.class, () -> ClientTls.fromEnv(Map.of("CAST_TLS_CERT", "c", "CAST_TLS_KEY", "k")));
    assertTrue(noCa.getMessage().contains("without CAST_TLS_CA"));
    InvalidArgumentError half =
        assertThrows(InvalidArgumentError.class, () -> ClientTls.fromEnv(Map.of("CAST_TLS_CA", "a", "CAST_TLS_CERT", "c")));
    assertTrue(half.getMessage().contains("set both CAST_TLS_CERT and CAST_TLS_KEY"));
    InvalidArgumentError unreadable =
        assertThrows(InvalidArgumentError.class, () -> Credentials.channelCredentials(new ClientTls(dir.resolve("none.pem").toString(), null, null, "")));
    assertTrue(unreadable.getMessage().contains("CAST_TLS_CA"), unreadable.getMessage());
  }
}
