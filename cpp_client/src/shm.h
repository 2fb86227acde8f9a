// Large values by shared memory with a server on this host: is there a
// session (docs/client-protocol.md, "Large values by shared memory", "The
// session, step by step"). Private to the gRPC transport. Mirrors the Python
// client's client/shm.py.
//
// Each server the transport reaches has a SharedLink. On first need it asks
// that server where its shared memory is (SystemDescription.shared_memory),
// connects to that Unix socket (abstract namespace: only reachable from the
// server's host, or its network namespace), checks that the server runs as
// this process's OS user, says HELLO with the token and gets WELCOME: a
// session id, the staging area (a memory file) and the threshold. If any of
// that fails, the link says why once at INFO and values travel as bytes;
// CAST_SHARED_MEMORY=off in the environment turns it off.
#pragma once

#include <chrono>
#include <functional>
#include <utility>
#include <vector>
#include <memory>
#include <mutex>
#include <stdexcept>
#include <string>

#include "cast/credentials.h"
#include "cast/errors.h"
#include "cast/log.h"
#include "cast/transport.h"
#include "cast/v1/directory.pb.h"
#include "shm_session.h"

namespace cast::detail {

// The environment variable that turns shared memory off in a process
// ("off", "0", "false", "no"; any case).
inline constexpr char kSharedMemoryEnv[] = "CAST_SHARED_MEMORY";

// Whether this process's environment turns shared memory off.
bool sharedMemoryTurnedOff();

// Why a session could not be opened.
class NoSession : public std::runtime_error {
 public:
  // `elsewhere`: the server's socket is not reachable from here (another host
  // or network namespace), so trying again soon is no use.
  NoSession(const std::string& why, bool elsewhere) : std::runtime_error(why), elsewhere(elsewhere) {}
  bool elsewhere;
};

// Opens a session with the server whose shared memory `info` names (the
// handshake bounded by 2 s); NoSession saying why not.
std::shared_ptr<ClientSession> connectShared(const v1::SharedMemoryInfo& info, const std::string& token,
                                             const std::string& endpoint);

// Shared memory with one server: its session, opened when first needed, or
// why there is none. Thread-safe.
class SharedLink {
 public:
  // `describe` asks the server itself (not the directory) for its
  // description; it throws what the call throws.
  using Describe = std::function<v1::SystemDescription()>;

  SharedLink(std::string endpoint, std::shared_ptr<TokenSource> tokens, Describe describe, Logger log);
  ~SharedLink();
  SharedLink(const SharedLink&) = delete;
  SharedLink& operator=(const SharedLink&) = delete;

  // Opens the session now, with what the server already said of itself
  // (its DescribeSystem answer), so that no later call waits for it.
  void open(const v1::SystemDescription& described);
  // The live session, opened now if there is none (at most every few seconds
  // after a failure); nullptr: values travel as bytes.
  std::shared_ptr<ClientSession> session();
  // A read call's part of the session (nullptr without one): its metadata,
  // and its end when the call is over.
  std::unique_ptr<ReadCall> read();
  // Reads what the server sent: a session it ended (a stream to it broke) is
  // noticed now, and what was mapped of it unmapped.
  void check();
  // Why values travel as bytes, while they do ("" with a session).
  std::string reason() const;
  // Ends the session; no other is opened.
  void close();

 private:
  // A new session, or nullptr (said once at INFO); `described`: the
  // server's description if known, else it is asked.
  std::shared_ptr<ClientSession> open(const v1::SystemDescription* described);
  void fallback(const std::string& why, std::chrono::seconds retry, bool forever = false);

  const std::string endpoint_;
  std::shared_ptr<TokenSource> tokens_;
  Describe describe_;
  Logger log_;
  std::mutex openMu_;      // held while a session is being opened
  mutable std::mutex mu_;  // guards what follows
  std::shared_ptr<ClientSession> session_;
  std::chrono::steady_clock::time_point retryAt_{};
  bool forever_ = false;  // turned off for good
  bool told_ = false;     // the fallback was said at INFO
  bool closed_ = false;
  std::string reason_;
};

// ------------------------------------------------------------------ writes
// docs/client-protocol.md, "Writing a large value".

// The values of one write request staged in shared memory, and the sessions
// they are staged in.
using Staging = std::vector<std::pair<std::shared_ptr<ClientSession>, Staged>>;

// An add or overwrite of `data`: `build(bytes)` makes the request with the
// bytes it carries, which are none when the value was staged in the session
// of `link` (large, on the server's host, room in the staging area; recorded
// in `staged` and named in the request).
v1::WriteRequest stagedWrite(SharedLink& link, const std::string& data, Staging& staged,
                             const std::function<v1::WriteRequest(const std::string& bytes)>& build);
// A batch of `ops`, its large values staged in the session of `link` (the
// server the batch goes to).
v1::WriteRequest stagedBatch(SharedLink& link, const std::vector<BatchOp>& ops, Staging& staged);
// The write is over (`error`: why it failed, nullptr if it did not): its
// staging regions are free again, unless its outcome is unknown (its stream
// broke, its deadline passed): the request may still be applied, and the
// server would copy whatever the regions then hold.
void unstage(const Staging& staged, const CastError* error);

}  // namespace cast::detail
