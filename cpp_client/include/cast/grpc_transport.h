// Reaching a CAST system over gRPC (docs/client-protocol.md): routing by SA
// through Directory.DescribeSystem, one Watch stream per server shared by all
// onChange registrations, a Heartbeat stream per server for the session, and
// the TaskManager decision stream. Like the Python client, it reconnects by
// itself: watches resume from the next revision they need (no gap, no
// duplicate; a server that lost that history makes watchFailed report
// HistoryExpiredError), sessions register again, decision streams reopen.
//
// The runner uses it; an embedding program or a test may bind a component to
// it directly:
//
//   component.bind(cast::connectGrpc(endpoint, token, {"id", "vision", false}));
#pragma once

#include <chrono>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>

#include "cast/transport.h"

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

// How connectGrpc talks to the system (the runner fills it from the launch
// contract; cast::connect from its ConnectOptions, see cast/connect.h).
struct TransportOptions {
  // Bounds every unary call except blocking locks.
  std::chrono::milliseconds callTimeout{30000};
  // TLS; plaintext without.
  std::optional<ClientTls> tls;
  // A file holding the current token (renewed by the orchestrator).
  std::string tokenFile;
};

// Connects to the directory at `endpoint` (host:port) and learns where each
// SA is served. Throws UnavailableError if the server cannot be reached,
// UnauthenticatedError if the token is refused, InvalidArgumentError for
// unreadable TLS files.
std::shared_ptr<detail::Transport> connectGrpc(const std::string& endpoint, const std::string& token,
                                               const Identity& identity, const TransportOptions& options = {});

}  // namespace cast
