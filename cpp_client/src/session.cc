// The component's sessions (session.h). Mirrors the Python client's
// client/session.py.
#include "session.h"

#include <unistd.h>

#include <algorithm>

#include "cast/version.h"

namespace cast::detail {

namespace {
// The deadline of one AwaitRun call: how soon a stop request is noticed while waiting.
constexpr Millis kAwaitRunPoll{1000};
}  // namespace

Session::Session(std::shared_ptr<TokenSource> tokens, Millis callTimeout, Logger log)
    : tokens_(std::move(tokens)), timeout_(callTimeout), log_(std::move(log)) {}

Session::~Session() { close(); }

void Session::start(const std::vector<Server*>& servers, const std::string& language, const std::string& kind,
                    StateSource state) {
  for (Server* s : servers) {
    Link* link;
    {
      std::lock_guard<std::mutex> lock(mu_);
      links_.push_back(std::make_unique<Link>(*s));
      link = links_.back().get();
    }
    const Millis interval = registerWith(*link, language, kind);
    link->thread = std::thread([this, link, interval, language, kind, state] {
      heartbeatLoop(*link, interval, language, kind, state);
    });
  }
}

std::optional<Identity> Session::verifiedIdentity() const {
  std::lock_guard<std::mutex> lock(mu_);
  return verified_;
}

void Session::stateChanged() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    ++stateVersion_;
  }
  wake_.notify_all();
}

bool Session::awaitRun(Server& directory, const StopWait& stopping) {
  Backoff backoff;
  const v1::AwaitRunRequest request;
  while (!stopping(Millis(0)) && !closingEvent_.isSet()) {
    try {
      unaryCall<v1::AwaitRunResponse>(*tokens_, kAwaitRunPoll, [&](auto* ctx, auto* r) {
        return directory.dir->AwaitRun(ctx, request, r);
      });
      return true;
    } catch (const CastError& e) {
      if (e.code() == "DEADLINE_EXCEEDED") continue;  // not released yet: ask again
      if (e.code() != "UNAVAILABLE") throw;
    }
    if (stopping(backoff.next())) break;
  }
  return false;
}

void Session::close() {
  std::vector<Link*> links;
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (closing_) return;
    closing_ = true;
    for (auto& link : links_) {
      links.push_back(link.get());
      if (link->context) link->context->TryCancel();
    }
  }
  wake_.notify_all();
  closingEvent_.set();
  for (Link* link : links) {
    if (link->thread.joinable()) link->thread.join();
  }
}

Millis Session::registerWith(Link& link, const std::string& language, const std::string& kind) {
  char host[256] = {0};
  ::gethostname(host, sizeof host - 1);
  v1::RegisterRequest req;
  req.set_language(language);
  req.set_kind(kind);
  req.set_pid(static_cast<std::int64_t>(::getpid()));
  req.set_host(host);
  req.set_library_version(libraryVersion());
  Server& s = link.server;
  auto resp = unaryCall<v1::RegisterResponse>(
      *tokens_, timeout_, [&](auto* ctx, auto* r) { return s.dir->Register(ctx, req, r); });
  std::lock_guard<std::mutex> lock(mu_);
  link.sessionId = resp.session_id();
  // The first answer is kept: every server verifies the same token, and a
  // registration after a reconnect must not change who a running component is.
  if (!verified_ && !resp.component_id().empty()) {
    verified_ = Identity{resp.component_id(), resp.subarchitecture(), resp.privileged()};
  }
  return Millis(std::max<std::int64_t>(50, resp.lease_ms() / 3));
}

// Keeps one server's session alive; a lost session (server restart, cut
// connection, lease expiry) is registered again with backoff: a new
// session, since the server released the old one's locks and tasks.
void Session::heartbeatLoop(Link& link, Millis interval, const std::string& language, const std::string& kind,
                            const StateSource& state) {
  Server& s = link.server;
  Backoff backoff;
  while (true) {
    auto context = std::make_shared<grpc::ClientContext>();
    std::string sessionId;
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (closing_) return;
      link.context = context;
      sessionId = link.sessionId;
    }
    authorize(*context, *tokens_);
    auto stream = s.dir->Heartbeat(context.get());
    v1::HeartbeatResponse response;
    std::uint64_t reported = 0;
    for (;;) {
      {
        std::lock_guard<std::mutex> lock(mu_);
        reported = stateVersion_;
      }
      v1::HeartbeatRequest beat;
      beat.set_session_id(sessionId);
      beat.set_state(static_cast<v1::ComponentState>(state()));
      if (!stream->Write(beat) || !stream->Read(&response)) break;
      backoff.reset();
      std::unique_lock<std::mutex> lock(mu_);
      // Wake early for a state change, so it is reported at once.
      wake_.wait_for(lock, interval, [&] { return closing_ || stateVersion_ != reported; });
      if (closing_) break;
    }
    context->TryCancel();
    const grpc::Status status = stream->Finish();
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (closing_) return;
    }
    // A server that died ended the shared-memory session too: unmap its memory now.
    if (s.shared) s.shared->check();
    log_.warning("session with " + s.endpoint + " lost (" + statusCodeName(status.error_code()) + ": " +
                 status.error_message() + "): its locks and tasks are released; registering again");
    while (!closingEvent_.wait(backoff.next())) {
      try {
        interval = registerWith(link, language, kind);
        log_.info("registered again with " + s.endpoint);
        break;
      } catch (const CastError& e) {
        log_.info("registering with " + s.endpoint + " failed (" + e.message() + "); retrying");
      }
    }
  }
}

}  // namespace cast::detail
