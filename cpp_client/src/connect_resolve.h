// How cast::connect finds the system, its token and TLS (cast/connect.h,
// docs/client-protocol.md "Scripts"), apart from connecting, so that the
// rules can be tested with an environment and a runtime directory of a test's
// own.
#pragma once

#include <cstdint>
#include <map>
#include <optional>
#include <string>

#include "cast/connect.h"

namespace cast::detail {

// What cast::connect found.
struct ConnectPlan {
  std::string endpoint;
  std::string endpointSource;  // where the endpoint came from, for error messages
  std::string token;
  std::string tokenFile;       // set when the token came from CAST_TOKEN_FILE: re-read when renewed
  Identity identity;           // what the token states
  std::optional<ClientTls> tls;
};

// Resolves `options` against `env` and the runtime directory; a minted token
// is issued at `now` (seconds since the epoch). NotFoundError (no system, no
// token or secret) or InvalidArgumentError (no SA for a minted token, options
// that contradict the token) saying what to give; UnauthenticatedError for a
// token that is no CAST token.
ConnectPlan resolveConnect(const ConnectOptions& options, const std::map<std::string, std::string>& env,
                           std::int64_t now);

// The component id of a minted token when none is given: script-<host>-<pid>.
std::string defaultScriptId();

// The token in the file CAST_TOKEN_FILE names, trimmed; InvalidArgumentError
// naming the variable and the path if it is empty or cannot be read. The file
// is the renewed token, so when it is set it is the token, not CAST_TOKEN: in
// cast::connect and in the runner's launch contract alike (and in Python and Java).
std::string readTokenFile(const std::string& path);

}  // namespace cast::detail
