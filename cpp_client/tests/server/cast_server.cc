// A real `cast serve` for tests (cast_server.h), on the testing kit.
#include "cast_server.h"

#include <ctime>

#include "cast/credentials.h"
#include "cast/testing.h"

namespace cast::testing {

CastServer::CastServer(std::vector<std::string> subarchitectures)
    : system_(std::make_unique<LocalSystem>(SystemOptions{std::move(subarchitectures), "", {}, std::chrono::seconds(90)})) {}

CastServer::~CastServer() = default;

const std::string& CastServer::endpoint() const { return system_->endpoint(); }

std::string CastServer::token(const std::string& componentId, const std::string& sa, bool privileged,
                              const std::string& secret) const {
  if (secret.empty()) return system_->token(componentId, sa, privileged);
  return mintToken(secret, Identity{componentId, sa, privileged}, static_cast<std::int64_t>(std::time(nullptr)));
}

std::unique_ptr<Connection> CastServer::connect(const std::string& componentId, const std::string& sa,
                                                TransportOptions options) const {
  return cast::connect(connectGrpc(endpoint(), token(componentId, sa), Identity{componentId, sa, false}, options));
}

void CastServer::kill() { system_->kill(); }

void CastServer::restart() { system_->restart(); }

std::string CastServer::log() const { return system_->output(); }

const std::string& CastServer::dir() const { return system_->directory(); }

CastServer& sharedServer() {
  static CastServer server;
  return server;
}

bool eventually(const std::function<bool()>& condition, std::chrono::milliseconds timeout) {
  try {
    waitFor(condition, timeout, "the condition");
    return true;
  } catch (const AssertionError&) {
    return false;
  }
}

std::future<std::string> lockOnAThread(Connection& component, const std::string& id, std::thread& thread) {
  auto outcome = std::make_shared<std::promise<std::string>>();
  thread = std::thread([&component, id, outcome] {
    try {
      component.lock(id, LockMode::OD, "", std::nullopt).release();
      outcome->set_value("granted");
    } catch (const UnavailableError& e) {
      outcome->set_value(e.message());
    } catch (const CastError& e) {
      outcome->set_value(std::string(e.name()) + ": " + e.message());
    }
  });
  return outcome->get_future();
}

}  // namespace cast::testing
