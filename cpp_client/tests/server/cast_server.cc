// A real `cast serve` for tests (cast_server.h), on the testing kit.
#include "cast_server.h"

#include <dirent.h>
#include <sys/socket.h>
#include <sys/un.h>

#include <cstdio>
#include <ctime>
#include <fstream>
#include <string>

#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include "cast/credentials.h"
#include "cast/v1/inspection.grpc.pb.h"
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

int endSessionSockets() {
  int ended = 0;
  DIR* dir = ::opendir("/proc/self/fd");
  while (dirent* e = ::readdir(dir)) {
    if (e->d_name[0] == '.') continue;
    const int fd = std::stoi(e->d_name);
    sockaddr_un peer{};
    socklen_t size = sizeof peer;
    if (::getpeername(fd, reinterpret_cast<sockaddr*>(&peer), &size) != 0 || peer.sun_family != AF_UNIX) continue;
    if (size <= sizeof(sa_family_t) + 1 || peer.sun_path[0] != '\0') continue;
    if (std::string(peer.sun_path + 1, 5) != "cast-") continue;
    ::shutdown(fd, SHUT_RDWR);
    ++ended;
  }
  ::closedir(dir);
  return ended;
}

cast::v1::SharedMemoryMetrics sharedMemoryFigures(const CastServer& server) {
  auto channel = grpc::CreateChannel(server.endpoint(), grpc::InsecureChannelCredentials());
  grpc::ClientContext ctx;
  ctx.AddMetadata("authorization", "Bearer " + server.token("shm-tool", "vision"));
  cast::v1::GetMetricsResponse resp;
  const grpc::Status status =
      cast::v1::Inspection::NewStub(channel)->GetMetrics(&ctx, cast::v1::GetMetricsRequest(), &resp);
  EXPECT_TRUE(status.ok()) << status.error_message();
  return resp.shared_memory();
}

void writeTokenFile(const std::string& path, const std::string& token) {
  {
    std::ofstream out(path + ".tmp");
    out << token;
  }
  std::rename((path + ".tmp").c_str(), path.c_str());
}

}  // namespace cast::testing
