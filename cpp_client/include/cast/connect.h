// Using a working memory from a plain program (a script, a tool, a test)
// rather than from a component that `cast run` launches:
//
//   auto wm = cast::connect();               // finds the running system
//   wm->add(wm->newId(), greeting);
//   auto watch = wm->onChange(cast::localTypeFilter<Greeting>(), [](const cast::WorkingMemoryChange& c) {...});
//
// A Connection has the working-memory calls, errors and watches of an
// unmanaged component (cast/component.h), with no lifecycle: nothing calls
// configure/start/run/stop. Callbacks run on its dispatcher thread. Its
// session (and with it its locks) ends when it is closed or destroyed.
//
// What connect() uses, each from the first place that has it
// (docs/client-protocol.md, "Scripts"):
//   endpoint  options.endpoint, $CAST_ENDPOINT, "endpoint" of <runtime dir>/system.json
//   token     options.token, the file $CAST_TOKEN_FILE, $CAST_TOKEN, else one minted
//             from the system's secret ($CAST_SECRET, the file $CAST_SECRET_FILE,
//             <runtime dir>/secret) for options.componentId (default
//             script-<host>-<pid>) in options.subarchitecture (default: the first SA
//             of the first server in system.json), privileged
//   TLS       options.tls, $CAST_TLS_*, the "tls" block of system.json; else plaintext
// The runtime dir is options.runtimeDir, else $CAST_RUNTIME_DIR, else .cast.
#pragma once

#include <chrono>
#include <memory>
#include <optional>
#include <string>

#include "cast/component.h"
#include "cast/grpc_transport.h"

namespace cast {

// Where and as whom cast::connect connects; every field is optional (empty:
// look it up as described above).
struct ConnectOptions {
  std::string endpoint;         // host:port of the system's directory
  std::string token;            // a token from `cast token`
  std::string componentId;      // the id of a minted token
  std::string subarchitecture;  // the own SA of a minted token
  std::string runtimeDir;       // where `cast run` keeps system.json and secret
  std::optional<ClientTls> tls; // TLS files (CA, client certificate and key, server name)
  // Bounds every unary call except blocking locks.
  std::chrono::milliseconds callTimeout{30000};
};

// A plain program's connection to a working memory system: the calls of an
// unmanaged component, with the same names (docs/client-protocol.md, "The
// vocabulary"). Every call may be made from any thread. Move it around as a
// std::unique_ptr; closing (or destroying) it ends its session.
class Connection final : private UnmanagedComponent {
 public:
  ~Connection() override = default;

  // Who this connection is: the identity its token states.
  using Component::componentId;
  using Component::privileged;
  using Component::subarchitecture;
  using Component::log;

  // Writes: newId, add, overwrite, addAsync, overwriteAsync, deleteEntry,
  // batch (cast/component.h); loan, for a large value written in place
  // (cast/loan.h).
  using Component::add;
  using Component::addAsync;
  using Component::overwriteAsync;
  using Component::batch;
  using Component::deleteEntry;
  using Component::newId;
  using Component::overwrite;
  using Component::loan;

  // Reads: get<T>, getEntry<T>, getAll<T>, getView, exists.
  using Component::exists;
  using Component::get;
  using Component::getAll;
  using Component::getEntry;
  using Component::getView;

  // Locks: lock (a LockGuard), tryLock, unlock.
  using Component::lock;
  using Component::tryLock;
  using Component::unlock;

  // Outcomes: report(name, value), kept by the server under this identity.
  using Component::report;

  // Watching: onChange with filters, callbacks on the dispatcher thread;
  // drain waits for the callbacks queued so far.
  using Component::drain;
  using Component::onChange;
  using Component::onDispatcherThread;

  // Ends the session (releasing its locks) after running the callbacks already
  // queued, and closes the channels. Idempotent; the destructor calls it too.
  using Component::close;

 private:
  friend std::unique_ptr<Connection> connect(std::shared_ptr<detail::Transport> transport);
  Connection() = default;
};

// Connects to the running system found as described at the top of this file.
// NotFoundError saying what to give when no system or token can be found
// (InvalidArgumentError for a missing subarchitecture or options that
// contradict the token), UnavailableError when nothing answers at the
// endpoint, UnauthenticatedError when the token is refused.
std::unique_ptr<Connection> connect(const ConnectOptions& options = {});

// A connection over a transport made by the caller (connectGrpc with options
// of its own, or a test double); its session starts now.
std::unique_ptr<Connection> connect(std::shared_ptr<detail::Transport> transport);

}  // namespace cast
