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
#include <memory>
#include <optional>
#include <string>

#include "cast/basic_types.h"
#include "cast/credentials.h"

namespace cast {

// The transport a component is bound to: internal (the library's
// src/transport.h); connectGrpc makes one.
namespace detail {
class Transport;
}  // namespace detail

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
// SA is served. The transport is opaque: bind a component to it, or give it
// to cast::connect or runComponent. Throws UnavailableError if the server
// cannot be reached, UnauthenticatedError if the token is refused,
// InvalidArgumentError for unreadable TLS files.
std::shared_ptr<detail::Transport> connectGrpc(const std::string& endpoint, const std::string& token,
                                               const Identity& identity, const TransportOptions& options = {});

}  // namespace cast
