package cast.client;

import java.util.Map;

/**
 * TLS settings of the launch contract: CAST_TLS_CA (the CA that signed the
 * servers' certificates; setting it turns TLS on, never falling back to
 * plaintext), CAST_TLS_CERT and CAST_TLS_KEY (the client's certificate chain and
 * PKCS#8 private key, for servers that require client certificates) and
 * CAST_TLS_SERVER_NAME (the name to verify the server certificate against).
 *
 * @param ca PEM file of the CA
 * @param cert PEM certificate chain of the client, or null
 * @param key PEM private key of the client, or null
 * @param serverName name to verify the server against, or "" for the host of the address
 */
public record ClientTls(String ca, String cert, String key, String serverName) {

  /** The settings in CAST_TLS_* variables; null without CAST_TLS_CA (plaintext). */
  public static ClientTls fromEnv(Map<String, String> env) {
    String ca = blankToNull(env.get("CAST_TLS_CA"));
    String cert = blankToNull(env.get("CAST_TLS_CERT"));
    String key = blankToNull(env.get("CAST_TLS_KEY"));
    if (ca == null) {
      if (cert != null || key != null) {
        throw new InvalidArgumentError("CAST_TLS_CERT/CAST_TLS_KEY given without CAST_TLS_CA: set the CA too");
      }
      return null;
    }
    if ((cert == null) != (key == null)) {
      throw new InvalidArgumentError("set both CAST_TLS_CERT and CAST_TLS_KEY, or neither");
    }
    String name = env.get("CAST_TLS_SERVER_NAME");
    return new ClientTls(ca, cert, key, name == null ? "" : name);
  }

  private static String blankToNull(String s) {
    return s == null || s.isEmpty() ? null : s;
  }
}
