// A client's credentials (docs/client-protocol.md, "Identity and metadata"):
// the component's token, fixed or renewed through a file, reading and minting
// tokens, and the TLS files of the connection.
//
// Tokens are JSON Web Tokens signed with HS256 and the system's secret,
//
//   base64url({"alg":"HS256","typ":"JWT"}) . base64url(claims) . base64url(HMAC-SHA256)
//
// with the claims {"c": component id, "s": SA, "p": privileged, "iat": issued}
// and "exp" when the token expires. The server verifies every token and tells
// a component who it is when it registers (RegisterResponse); a client reads
// the claims only where it must know them before that (cast::connect), and
// mints a token itself only when it holds the system's secret (a script).
//
// This is the public header of credentials.cc.
#pragma once

#include <chrono>
#include <cstdint>
#include <map>
#include <mutex>
#include <optional>
#include <string>
#include <utility>

#include "cast/basic_types.h"

namespace cast {

// TLS settings of a client (CAST_TLS_CA, CAST_TLS_CERT, CAST_TLS_KEY,
// CAST_TLS_SERVER_NAME): PEM files of the CA that signed the servers'
// certificates, and optionally the client's own certificate and key.
struct ClientTls {
  std::string ca;
  std::string cert;
  std::string key;
  std::string serverName;  // name to verify the server certificate against, if not the host

  // The settings in the environment; nullopt without CAST_TLS_CA (plaintext).
  // InvalidArgumentError for an incomplete set.
  static std::optional<ClientTls> fromEnv(const std::map<std::string, std::string>& env);
};

// The component's current token: fixed, or re-read from a file that the
// orchestrator rewrites before the token expires (CAST_TOKEN_FILE). The file
// is checked at most every `checkInterval` (one stat) and re-read only when
// it changed; an empty or unreadable file keeps the last token.
class TokenSource {
 public:
  explicit TokenSource(std::string token, std::string path = "",
                       std::chrono::milliseconds checkInterval = std::chrono::milliseconds(1000));
  // The token to send now.
  std::string token();
  // Re-reads the file now (after the server refused the token); true if the
  // token changed.
  bool refresh();
  // The token file; empty for a fixed token.
  const std::string& path() const { return path_; }

 private:
  void reload(bool force);
  std::mutex mu_;
  std::string token_;
  std::string path_;
  std::chrono::milliseconds interval_;
  std::chrono::steady_clock::time_point checked_{};
  std::pair<long long, long long> stamp_{-1, -1};  // mtime ns, size
};

// What a token says about its holder, read without verifying it; nullopt if
// it is not a CAST token (a JWT whose claims carry "c", "s" and "p").
std::optional<Identity> peekToken(const std::string& token);

// A token for `identity` signed with `secret`, issued at `issuedAt` (seconds
// since the epoch), with no expiry: what `cast token` would issue. The server
// accepts it if `secret` is the system's secret. InvalidArgumentError for a
// secret shorter than 32 bytes, which HS256 does not allow (RFC 7518, 3.2).
std::string mintToken(const std::string& secret, const Identity& identity, std::int64_t issuedAt);

}  // namespace cast
