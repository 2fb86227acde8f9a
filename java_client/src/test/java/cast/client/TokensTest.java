package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import java.nio.charset.StandardCharsets;
import java.util.Base64;
import org.junit.jupiter.api.Test;

/** Tokens are JWTs (HS256): minting one byte for byte as PyJWT does. */
class TokensTest {
  static final byte[] SECRET = "test-secret-0123456789abcdef-0123456789".getBytes(StandardCharsets.UTF_8);
  /** PyJWT: {"c": "planner", "s": "coordination", "p": true, "iat": 1700000000, "exp": 1700003600}. */
  static final String PLANNER_TOKEN =
      "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9."
          + "eyJjIjoicGxhbm5lciIsInMiOiJjb29yZGluYXRpb24iLCJwIjp0cnVlLCJpYXQiOjE3MDAwMDAwMDAsImV4cCI6MTcwMDAwMzYwMH0."
          + "mON1cpsY000YjhzfewPiFgGFw69BHVWWsbe6zfS8uGs";
  /** PyJWT: {"c": "worker", "s": "vision", "p": false, "iat": 1700000000}. */
  static final String WORKER_TOKEN =
      "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9."
          + "eyJjIjoid29ya2VyIiwicyI6InZpc2lvbiIsInAiOmZhbHNlLCJpYXQiOjE3MDAwMDAwMDB9."
          + "be7w-IN7v4b7UGcmj70cE90WGKwP6lZcQm1wWFs03v0";

  @Test
  void hs256MatchesAKnownVector() {
    // The example of jwt.io (RFC 7519's header and claims, secret "your-256-bit-secret").
    assertEquals(
        "SflKxwRJSMeKKF2QT4fwpMeJf36POk6yJV_adQssw5c",
        Tokens.signHs256(
            "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9."
                + "eyJzdWIiOiIxMjM0NTY3ODkwIiwibmFtZSI6IkpvaG4gRG9lIiwiaWF0IjoxNTE2MjM5MDIyfQ",
            "your-256-bit-secret".getBytes(StandardCharsets.UTF_8)));
  }

  @Test
  void mintedTokensAreThoseTheServerIssues() {
    assertEquals(
        "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9."
            + "eyJjIjoic2NyaXB0LWhvc3QtNDIiLCJzIjoidmlzaW9uIiwicCI6dHJ1ZSwiaWF0IjoxNzAwMDAwMDAwfQ."
            + "GV9K--yQT7Hfsi6RLHqlQeHX0ueUeZ6KSM-C3i3AQIk",
        Tokens.mint(SECRET, new Identity("script-host-42", "vision", true), 1_700_000_000L));
    assertEquals(WORKER_TOKEN, Tokens.mint(SECRET, new Identity("worker", "vision", false), 1_700_000_000L));
    // Quotes, backslashes and control characters are escaped as json.dumps escapes them.
    String odd = Tokens.mint(SECRET, new Identity("a \"quoted\" \\ id\n", "vision", true), 1_700_000_000L);
    assertEquals(
        "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9."
            + "eyJjIjoiYSBcInF1b3RlZFwiIFxcIGlkXG4iLCJzIjoidmlzaW9uIiwicCI6dHJ1ZSwiaWF0IjoxNzAwMDAwMDAwfQ."
            + "8_nm3PI22a7mqz0tm6WHCR9nmdfGFnHYpWC9iaSRNFo",
        odd);
    assertEquals(
        "{\"c\":\"a \\\"quoted\\\" \\\\ id\\n\",\"s\":\"vision\",\"p\":true,\"iat\":1700000000}",
        new String(Base64.getUrlDecoder().decode(odd.split("\\.")[1]), StandardCharsets.UTF_8));
  }

  @Test
  void mintingWithAShortSecretSaysWhy() {
    InvalidArgumentError e =
        assertThrows(
            InvalidArgumentError.class,
            () -> Tokens.mint("short".getBytes(StandardCharsets.UTF_8), new Identity("x", "vision", true), 1));
    assertTrue(e.getMessage().contains("5 bytes, shorter than 32"), e.getMessage());
  }
}
