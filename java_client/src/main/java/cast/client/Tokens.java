package cast.client;

import java.nio.charset.StandardCharsets;
import java.security.GeneralSecurityException;
import java.util.Base64;
import javax.crypto.Mac;
import javax.crypto.spec.SecretKeySpec;

/**
 * Component tokens (docs/client-protocol.md, "Identity and metadata"): JSON Web
 * Tokens signed with HS256 and the system's secret,
 * {@code base64url({"alg":"HS256","typ":"JWT"}).base64url(claims).base64url(HMAC-SHA256)},
 * with the claims {@code {"c": component id, "s": SA, "p": privileged, "iat": issued}}
 * and {@code "exp"} when the token expires. The server verifies every token and
 * says whom it was issued to when a component registers; a client never decodes
 * one, and mints one itself only when it holds the system's secret
 * ({@link Cast#connect} from a script).
 */
public final class Tokens {
  /** The header every CAST token has, already encoded: {"alg":"HS256","typ":"JWT"}. */
  static final String HEADER = "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9";
  /** HS256 keys must be at least as long as the hash (RFC 7518, 3.2). */
  static final int MIN_SECRET = 32;

  private Tokens() {}

  /**
   * A token for {@code identity} signed with {@code secret}, issued at {@code issuedAt}
   * (seconds since the epoch), with no expiry: what {@code cast token} would issue.
   * InvalidArgumentError for a secret shorter than 32 bytes, which HS256 does not allow.
   */
  public static String mint(byte[] secret, Identity identity, long issuedAt) {
    if (secret.length < MIN_SECRET) {
      throw new InvalidArgumentError(
          "the token secret is "
              + secret.length
              + " bytes, shorter than 32: HS256 needs at least 32 bytes; use the secret of the running system"
              + " (`cast run` writes it to <runtime dir>/secret)");
    }
    // The claims in the order cast.auth.TokenSigner writes them.
    String claims =
        "{\"c\":"
            + jsonString(identity.componentId())
            + ",\"s\":"
            + jsonString(identity.subarchitecture())
            + ",\"p\":"
            + identity.privileged()
            + ",\"iat\":"
            + issuedAt
            + "}";
    String signingInput = HEADER + "." + base64Url(claims.getBytes(StandardCharsets.UTF_8));
    return signingInput + "." + signHs256(signingInput, secret);
  }

  /** base64url without padding (RFC 7515, section 2), as JWTs write their parts. */
  static String base64Url(byte[] bytes) {
    return Base64.getUrlEncoder().withoutPadding().encodeToString(bytes);
  }

  /** The JWT signature of {@code signingInput} ("header.payload"): base64url(HMAC-SHA256(secret, input)). */
  static String signHs256(String signingInput, byte[] secret) {
    try {
      Mac mac = Mac.getInstance("HmacSHA256");
      mac.init(new SecretKeySpec(secret, "HmacSHA256"));
      return base64Url(mac.doFinal(signingInput.getBytes(StandardCharsets.UTF_8)));
    } catch (GeneralSecurityException e) { // every JDK has HmacSHA256
      throw new InternalError("HMAC-SHA256 is not available in this JVM: " + e.getMessage());
    }
  }

  /**
   * A JSON string literal, escaped as Python's json.dumps escapes ASCII, so a token
   * minted here for an ASCII id is byte for byte the one {@code cast token} mints.
   */
  static String jsonString(String text) {
    StringBuilder out = new StringBuilder("\"");
    for (int i = 0; i < text.length(); i++) {
      char ch = text.charAt(i);
      switch (ch) {
        case '"' -> out.append("\\\"");
        case '\\' -> out.append("\\\\");
        case '\n' -> out.append("\\n");
        case '\r' -> out.append("\\r");
        case '\t' -> out.append("\\t");
        case '\b' -> out.append("\\b");
        case '\f' -> out.append("\\f");
        default -> {
          if (ch < 0x20) {
            out.append(String.format("\\u%04x", (int) ch));
          } else {
            out.append(ch); // non-ASCII goes out as UTF-8: valid JSON
          }
        }
      }
    }
    return out.append('"').toString();
  }
}
