// The component's sessions (docs/client-protocol.md, "Start-up" step 3 and
// "Reconnecting"): Register with every server, a Heartbeat stream per server
// that keeps the session alive and reports the component's state, a new
// registration when a session was lost, and the wait at the start barrier
// (Directory.AwaitRun). Private to the gRPC transport.
#pragma once

#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "backoff.h"
#include "cast/log.h"
#include "transport.h"
#include "grpc_server.h"

namespace cast::detail {

class Session {
 public:
  // `callTimeout` bounds each Register call; `log` names the component.
  Session(std::shared_ptr<TokenSource> tokens, Millis callTimeout, Logger log);
  ~Session();
  Session(const Session&) = delete;
  Session& operator=(const Session&) = delete;

  // Registers with each of `servers` in turn (the directory first: its answer
  // says who the component is) and starts its heartbeat; throws
  // what a refused or failed Register throws (heartbeats already started end
  // with close()).
  void start(const std::vector<Server*>& servers, const std::string& language, const std::string& kind,
             StateSource state);
  // The identity the first server registered with verified from the token
  // (RegisterResponse); nullopt before start() or if that server does not
  // say (one older than RegisterResponse's identity fields).
  std::optional<Identity> verifiedIdentity() const;
  // Reports the component's state now rather than at the next heartbeat.
  void stateChanged();
  // Long-polls `directory`'s AwaitRun until the start barrier is released
  // (true) or `stopping` says the component was asked to stop, or close()
  // was called (false). Each call has a short deadline, so a stop request is
  // seen within it; a server that is away is asked again with backoff; any
  // other error is thrown.
  bool awaitRun(Server& directory, const StopWait& stopping);
  // Ends every session and joins the heartbeat threads. Ending a heartbeat
  // stream ends its session: the server releases this component's locks and
  // tasks at once rather than at lease expiry.
  void close();

 private:
  // The session with one server.
  struct Link {
    explicit Link(Server& s) : server(s) {}
    Server& server;
    std::string sessionId;                          // guarded by mu_
    std::shared_ptr<grpc::ClientContext> context;   // of the open Heartbeat call; guarded by mu_
    std::thread thread;
  };

  Millis registerWith(Link& link, const std::string& language, const std::string& kind);
  void heartbeatLoop(Link& link, Millis interval, const std::string& language, const std::string& kind,
                     const StateSource& state);

  std::shared_ptr<TokenSource> tokens_;
  Millis timeout_;
  Logger log_;
  mutable std::mutex mu_;
  std::condition_variable wake_;  // a state change or close(): heartbeat at once
  bool closing_ = false;          // guarded by mu_; closingEvent_ is the same, for interruptible waits
  Closing closingEvent_;
  std::uint64_t stateVersion_ = 0;  // bumped by stateChanged(); guarded by mu_
  std::vector<std::unique_ptr<Link>> links_;  // guarded by mu_
  std::optional<Identity> verified_;          // guarded by mu_
};

}  // namespace cast::detail
