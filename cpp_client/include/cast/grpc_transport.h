// Reaching a CAST system over gRPC (docs/client-protocol.md): routing by SA
// through Directory.DescribeSystem, one Watch stream per server shared by all
// onChange registrations, a Heartbeat stream per server for the session, and
// the TaskManager decision stream. The runner uses it; an embedding program
// or a test may bind a component to it directly:
//
//   component.bind(cast::connectGrpc(endpoint, token, {"id", "vision", false}));
#pragma once

#include <chrono>
#include <memory>
#include <string>

#include "cast/transport.h"

namespace cast {

// Connects to the directory at `endpoint` (host:port) and learns where each
// SA is served. `callTimeout` bounds every unary call except blocking locks.
// Throws UnavailableError if the server cannot be reached,
// UnauthenticatedError if the token is refused.
std::shared_ptr<detail::Transport> connectGrpc(
    const std::string& endpoint, const std::string& token, const Identity& identity,
    std::chrono::milliseconds callTimeout = std::chrono::milliseconds(30000));

}  // namespace cast
