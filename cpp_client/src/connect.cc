#include "cast/connect.h"

#include <ctime>

#include "connect_resolve.h"
#include "process_env.h"

namespace cast {

std::unique_ptr<Connection> connect(const ConnectOptions& options) {
  const detail::ConnectPlan plan =
      detail::resolveConnect(options, detail::processEnv(), static_cast<std::int64_t>(std::time(nullptr)));
  TransportOptions transport;
  transport.callTimeout = options.callTimeout;
  transport.tls = plan.tls;
  transport.tokenFile = plan.tokenFile;
  try {
    return connect(connectGrpc(plan.endpoint, plan.token, plan.identity, transport));
  } catch (const UnavailableError& e) {
    // Say where the address came from: a stale system.json or CAST_ENDPOINT is the usual cause.
    throw UnavailableError("no CAST system answers at " + plan.endpoint + " (from " + plan.endpointSource +
                           (plan.tls ? ", spoken to with TLS" : ", spoken to in plaintext") + "): " + e.message());
  }
}

std::unique_ptr<Connection> connect(std::shared_ptr<detail::Transport> transport) {
  std::unique_ptr<Connection> connection(new Connection());
  connection->bind(std::move(transport));
  // Nothing else will run: tools show the session as RUNNING from the start.
  connection->setState(ComponentState::Running);
  return connection;
}

}  // namespace cast
