// A real `cast serve` for the C++ tests that need the server's side of the
// wire (the Write stream, delivery policies): the testing kit's LocalSystem
// (cast/testing.h), with the few words these tests use. The server is the
// repository's own, which ctest names in CAST_SERVE (make test-cpp sets up
// .venv first).
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <future>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include <google/protobuf/wrappers.pb.h>

#include "cast/connect.h"
#include "cast/v1/inspection.pb.h"
#include "cast/grpc_transport.h"
#include "transport.h"

namespace cast::testing {

class LocalSystem;

class CastServer {
 public:
  // A system of these SAs, its server started on a free port.
  explicit CastServer(std::vector<std::string> subarchitectures = {"vision", "language", "motor"});
  ~CastServer();
  CastServer(const CastServer&) = delete;
  CastServer& operator=(const CastServer&) = delete;

  // host:port of the running server.
  const std::string& endpoint() const;
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
  const std::string& dir() const;

 private:
  std::unique_ptr<LocalSystem> system_;
};

// One server shared by the tests of a binary (started by the first that asks).
CastServer& sharedServer();

// Polls `condition` (cast::testing::waitFor) until it holds or `timeout`
// passes; whether it held.
bool eventually(const std::function<bool()>& condition, std::chrono::milliseconds timeout = std::chrono::seconds(20));

// Ends every connection of this process to a server's shared-memory socket
// (its peer is bound to the abstract name "cast-..."): those sessions end as
// if the server had closed them. How many it ended.
int endSessionSockets();

// Replaces the token file at `path` whole, as the orchestrator renews it.
void writeTokenFile(const std::string& path, const std::string& token);

inline constexpr std::size_t kMiB = std::size_t{1} << 20;

// An Int64Value holding `n`, the entry type of most of these tests.
inline google::protobuf::Int64Value number(std::int64_t n) {
  google::protobuf::Int64Value v;
  v.set_value(n);
  return v;
}

// A BytesValue of `size` bytes that differ from one `seed` to the next (an
// image-sized value when `size` is large).
inline google::protobuf::BytesValue image(std::size_t size, int seed) {
  std::string bytes(size, '\0');
  for (std::size_t i = 0; i < size; ++i) bytes[i] = static_cast<char>((seed * 7 + i) % 251);
  google::protobuf::BytesValue v;
  v.set_value(std::move(bytes));
  return v;
}

// The server's shared-memory figures (Inspection.GetMetrics), asked as a
// tool component of "vision": which path a value took, what is lent.
cast::v1::SharedMemoryMetrics sharedMemoryFigures(const CastServer& server);

// Whether `text` (an error's message, a log) holds `part`.
inline bool contains(const std::string& text, const std::string& part) { return text.find(part) != std::string::npos; }

// Asks for `id`'s lock (OD, no timeout) on `thread`, which the caller joins:
// the future holds "granted", an UnavailableError's message, or another
// error's name and message (tests of what ends a waiting lock).
std::future<std::string> lockOnAThread(Connection& component, const std::string& id, std::thread& thread);

}  // namespace cast::testing
