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
#include <memory>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "cast/credentials.h"
#include "cast/errors.h"
#include "cast/log.h"
#include "transport.h"
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

// The handshake's own bound (docs/client-protocol.md: 2 s).
inline constexpr std::chrono::milliseconds kConnectWait{2000};

// Opens a session with the server whose shared memory `info` names, the
// handshake bounded by `within` (at most kConnectWait); NoSession saying why
// not.
std::shared_ptr<ClientSession> connectShared(const v1::SharedMemoryInfo& info, const std::string& token,
                                             const std::string& endpoint,
                                             std::chrono::milliseconds within = kConnectWait);

// Shared memory with one server: its session, opened when first needed, or
// why there is none. Thread-safe.
class SharedLink {
 public:
  // How long an opening may take: what is left of the call that needs the
  // session (nullopt: the opening's own bounds).
  using Within = std::optional<std::chrono::milliseconds>;
  // `describe` asks the server itself (not the directory) for its
  // description, within the given time (nullopt: its own bound); it throws
  // what the call throws.
  using Describe = std::function<v1::SystemDescription(Within)>;

  SharedLink(std::string endpoint, std::shared_ptr<TokenSource> tokens, Describe describe, Logger log);
  ~SharedLink();
  SharedLink(const SharedLink&) = delete;
  SharedLink& operator=(const SharedLink&) = delete;

  // Opens the session now, with what the server already said of itself
  // (its DescribeSystem answer), so that no later call waits for it.
  void open(const v1::SystemDescription& described);
  // The live session, opened now if there is none (at most every few seconds
  // after a failure); nullptr: values travel as bytes. `within`: the longest
  // the opening may take, waiting for another thread's opening included (a
  // call's time left: opening on a call's way spends the call's time).
  std::shared_ptr<ClientSession> session(Within within = std::nullopt);
  // session() for a write sent with the token in force now: a session
  // opened with an older one (the token was renewed) ends first, after its
  // outstanding writes (renew), so that a value is staged in the session its
  // write goes on, with the new token's identity.
  std::shared_ptr<ClientSession> writerSession(Within within = std::nullopt);
  // The live session, never opening one (nullptr: none).
  std::shared_ptr<ClientSession> current() const;
  // A read call's part of the session (nullptr without one): its metadata,
  // and its end when the call is over. `within` as for session().
  // `currentToken`: a read sent on the session's socket, which carries its
  // HELLO's identity as a write does: the session is writerSession()'s.
  std::unique_ptr<ReadCall> read(Within within = std::nullopt, bool currentToken = false);
  // Reads what the server sent: a session it ended (a stream to it broke) is
  // noticed now, and what was mapped of it unmapped.
  void check();
  // Why values travel as bytes, while they do ("" with a session).
  std::string reason() const;
  // The token was renewed: the session (whose writes carry the token of its
  // HELLO) ends once its outstanding writes were answered (up to `drain`),
  // and the next use opens one with the new token.
  void renew(std::chrono::milliseconds drain);
  // Ends the session; no other is opened.
  void close();

 private:
  // A new session, or nullptr (said once at INFO); `described`: the
  // server's description if known, else it is asked.
  std::shared_ptr<ClientSession> open(const v1::SystemDescription* described, Within within);
  void fallback(const std::string& why, std::chrono::seconds retry, bool forever = false);

  const std::string endpoint_;
  std::shared_ptr<TokenSource> tokens_;
  Describe describe_;
  Logger log_;
  std::timed_mutex openMu_;  // held while a session is being opened
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
// in `staged` and named in the request). `within`: the longest opening the
// session may take (the write's time left).
v1::WriteRequest stagedWrite(SharedLink& link, const std::string& data, Staging& staged,
                             const std::function<v1::WriteRequest(const std::string& bytes)>& build,
                             SharedLink::Within within);
// The same for a value given as its message: when it is staged, it is
// serialised straight into the staging area (no bytes of it in between).
v1::WriteRequest stagedMessage(SharedLink& link, const google::protobuf::Message& value, Staging& staged,
                               const std::function<v1::WriteRequest(const std::string& bytes)>& build,
                               SharedLink::Within within);

// A loan (loan_state.h) of `size` bytes after `header`: placed in a region
// of the staging area of the session of `link` (the writer's session, as a
// staged value's) when header + size reach its threshold and a region fits,
// its payload on a 64-byte line there; else private memory. `within`: the
// longest opening the session may take.
std::unique_ptr<LoanState> placeLoan(SharedLink& link, std::string header, std::size_t size,
                                     SharedLink::Within within);
// An add or overwrite of a loan's value: when the loan's region is in the
// session of `link` the write goes on (still live, not replaced), the request
// names it with no copy (recorded in `staged`, given back by unstage as a
// staged value's); else its bytes go as stagedWrite sends bytes (staged
// again in the live session if there is one).
v1::WriteRequest loanedWrite(SharedLink& link, LoanState& loan, Staging& staged,
                             const std::function<v1::WriteRequest(const std::string& bytes)>& build,
                             SharedLink::Within within);

// A batch of `ops`, its large values staged in the session of `link` (the
// server the batch goes to).
v1::WriteRequest stagedBatch(SharedLink& link, const std::vector<BatchOp>& ops, Staging& staged,
                             SharedLink::Within within);
// The write is over (`error`: why it failed, nullptr if it did not): its
// staging regions are free again, unless its outcome is unknown (its stream
// broke, its deadline passed): the request may still be applied, and the
// server would copy whatever the regions then hold.
void unstage(const Staging& staged, const CastError* error);

}  // namespace cast::detail
