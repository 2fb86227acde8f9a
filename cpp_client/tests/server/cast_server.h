// A real `cast serve` for the C++ tests that need the server's side of the
// wire (the Write stream, delivery policies): the repository's own Python
// server, started from .venv on a port the system picks (never a fixed one),
// memory only, with a test secret so the tests mint their components' tokens.
//
// It needs `make setup proto` (make test-cpp does them): a missing .venv
// fails the test with that advice, it never skips.
#pragma once

#include <sys/types.h>

#include <chrono>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "cast/connect.h"
#include "cast/grpc_transport.h"

namespace cast::testing {

class CastServer {
 public:
  // Starts `cast serve` for a system of these SAs and waits (up to 30 s) for
  // its "listening on" line; throws std::runtime_error with its log if it
  // does not come.
  explicit CastServer(std::vector<std::string> subarchitectures = {"vision", "language", "motor"});
  ~CastServer();
  CastServer(const CastServer&) = delete;
  CastServer& operator=(const CastServer&) = delete;

  // host:port of the running server.
  const std::string& endpoint() const { return endpoint_; }
  // A token for a component, signed with the server's secret (`secret`:
  // another one, which the server refuses).
  std::string token(const std::string& componentId, const std::string& sa, bool privileged = false,
                    const std::string& secret = "") const;
  // A script's connection as `componentId` of `sa`, with a live session.
  std::unique_ptr<Connection> connect(const std::string& componentId, const std::string& sa,
                                      TransportOptions options = {}) const;
  // SIGKILL: the server is gone at once, its connections break.
  void kill();
  // Starts the server again on the same port (a new, empty system).
  void restart();
  // What the server printed so far (for failure messages).
  std::string log() const;
  // A directory of the test's own, removed with the server.
  const std::string& dir() const { return dir_; }

 private:
  void start(const std::string& listen);
  std::string dir_;
  pid_t pid_ = -1;
  std::string endpoint_;
};

// One server shared by the tests of a binary (started by the first that asks).
CastServer& sharedServer();

// Polls `condition` every 10 ms until it holds or `timeout` passes; its last answer.
bool waitFor(const std::function<bool()>& condition, std::chrono::milliseconds timeout = std::chrono::seconds(20));

}  // namespace cast::testing
