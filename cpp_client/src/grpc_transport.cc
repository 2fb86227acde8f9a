// The gRPC transport: docs/client-protocol.md, call by call. Mirrors the
// Python reference client (python/cast/client/grpc_transport.py).
#include "cast/grpc_transport.h"

#include <grpcpp/grpcpp.h>
#include <unistd.h>

#include <atomic>
#include <condition_variable>
#include <mutex>
#include <thread>

#include "cast/log.h"
#include "cast/v1/directory.grpc.pb.h"
#include "cast/v1/task_manager.grpc.pb.h"
#include "cast/v1/working_memory.grpc.pb.h"

namespace cast {
namespace detail {
namespace {

constexpr char kTypeUrlPrefix[] = "type.googleapis.com/";
constexpr int kMaxMessageBytes = 64 * 1024 * 1024;

using Millis = std::chrono::milliseconds;

// ------------------------------------------------------------ conversions

v1::EntryAddress addressPb(const std::string& sa, const std::string& id) {
  v1::EntryAddress a;
  a.set_id(id);
  a.set_subarchitecture(sa);
  return a;
}

void setAny(google::protobuf::Any* any, const std::string& type, const std::string& data) {
  any->set_type_url(kTypeUrlPrefix + type);
  any->set_value(data);
}

std::string typeFromUrl(const std::string& url) {
  const auto slash = url.rfind('/');
  return slash == std::string::npos ? url : url.substr(slash + 1);
}

std::int64_t nanos(const google::protobuf::Timestamp& t) {
  return static_cast<std::int64_t>(t.seconds()) * 1000000000LL + t.nanos();
}

EntryRecord entryFromPb(const v1::Entry& e) {
  EntryRecord r;
  r.address = WorkingMemoryAddress{e.address().id(), e.address().subarchitecture()};
  r.type = e.type();
  r.data = e.value().value();
  r.version = e.version();
  r.author = e.author();
  r.revision = e.revision();
  r.modifiedNs = nanos(e.modified());
  return r;
}

EventRecord eventFromPb(const v1::ChangeEvent& e) {
  EventRecord r;
  r.revision = e.revision();
  r.operation = static_cast<Operation>(e.operation());
  r.address = WorkingMemoryAddress{e.address().id(), e.address().subarchitecture()};
  r.type = e.type();
  r.sourceComponent = e.source_component();
  r.sourceSubarchitecture = e.source_subarchitecture();
  r.version = e.version();
  r.timeNs = nanos(e.time());
  if (e.has_entry()) r.entry = entryFromPb(e.entry());
  return r;
}

TaskRecord taskFromPb(const v1::Task& t) {
  TaskRecord r;
  r.taskId = t.task_id();
  r.name = t.name();
  r.subarchitecture = t.subarchitecture();
  r.component = t.component();
  r.priority = t.priority();
  r.state = static_cast<TaskState>(t.state());
  r.outcome = static_cast<TaskOutcome>(t.outcome());
  r.reason = t.reason();
  if (t.has_data() && !t.data().type_url().empty()) {
    r.dataType = typeFromUrl(t.data().type_url());
    r.data = t.data().value();
  }
  return r;
}

void filterToPb(const ChangeFilter& f, v1::ChangeFilter* pb) {
  for (Operation op : f.operations) pb->add_operations(static_cast<v1::Operation>(op));
  pb->set_type(f.type);
  pb->set_id(f.id);
  pb->set_subarchitecture(f.subarchitecture);
  pb->set_source_component(f.sourceComponent);
  pb->set_source_subarchitecture(f.sourceSubarchitecture);
  pb->set_include_entry(f.includeEntry);
}

WriteResult writeResult(const v1::WriteResponse& r) { return WriteResult{r.revision(), r.version()}; }

// ------------------------------------------------------------ one server

class WatchStream;

struct Server {
  explicit Server(std::string ep) : endpoint(std::move(ep)) {
    grpc::ChannelArguments args;
    args.SetMaxSendMessageSize(kMaxMessageBytes);
    args.SetMaxReceiveMessageSize(kMaxMessageBytes);
    // Keepalive so that a server that vanished (host down, cable pulled) is
    // noticed by the streams, as in the Python client.
    args.SetInt(GRPC_ARG_KEEPALIVE_TIME_MS, 10000);
    args.SetInt(GRPC_ARG_KEEPALIVE_TIMEOUT_MS, 5000);
    args.SetInt(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
    channel = grpc::CreateCustomChannel(endpoint, grpc::InsecureChannelCredentials(), args);
    wm = v1::WorkingMemory::NewStub(channel);
    tm = v1::TaskManager::NewStub(channel);
    dir = v1::Directory::NewStub(channel);
  }

  std::string endpoint;
  std::shared_ptr<grpc::Channel> channel;
  std::unique_ptr<v1::WorkingMemory::Stub> wm;
  std::unique_ptr<v1::TaskManager::Stub> tm;
  std::unique_ptr<v1::Directory::Stub> dir;
  std::shared_ptr<WatchStream> watch;  // guarded by GrpcTransport::mu_
  std::string sessionId;
  std::unique_ptr<grpc::ClientContext> heartbeatContext;
  std::thread heartbeat;
};

// ------------------------------------------------------------ watch stream

// One Watch call to one server, shared by every watch of the component there.
class WatchStream {
 public:
  WatchStream(Server& server, const std::string& authorization, EventSink sink, ErrorSink onError)
      : endpoint_(server.endpoint), sink_(std::move(sink)), onError_(std::move(onError)) {
    context_.AddMetadata("authorization", authorization);
    stream_ = server.wm->Watch(&context_);
    reader_ = std::thread([this] { readLoop(); });
  }

  ~WatchStream() { close(); }

  bool dead() {
    std::lock_guard<std::mutex> lock(mu_);
    return dead_;
  }

  std::map<std::string, std::uint64_t> create(std::uint32_t watchId, const std::vector<ChangeFilter>& filters,
                                              const std::map<std::string, std::uint64_t>& starts, Millis timeout) {
    auto pending = std::make_shared<Pending>();
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (dead_) deathError_->raise();
      pending_[watchId] = pending;
    }
    v1::WatchRequest request;
    auto* create = request.mutable_create();
    create->set_watch_id(watchId);
    for (const auto& f : filters) filterToPb(f, create->add_filters());
    for (const auto& kv : starts) (*create->mutable_start_revisions())[kv.first] = kv.second;
    // A failed write means the stream broke; the reader then resolves every
    // pending create with the stream's final status, so just wait below.
    write(request);
    std::unique_lock<std::mutex> lock(mu_);
    if (!cv_.wait_for(lock, timeout, [&] { return pending->done; })) {
      pending_.erase(watchId);
      throw DeadlineExceededError("the server at " + endpoint_ + " did not confirm watch " +
                                  std::to_string(watchId) + " within " + std::to_string(timeout.count()) + " ms");
    }
    if (pending->error) pending->error->raise();
    return pending->revisions;
  }

  void cancel(std::uint32_t watchId) {
    v1::WatchRequest request;
    request.mutable_cancel()->set_watch_id(watchId);
    write(request);
  }

  void close() {
    if (closed_.exchange(true)) return;
    context_.TryCancel();
    if (reader_.joinable()) reader_.join();
  }

 private:
  struct Pending {
    bool done = false;
    std::map<std::string, std::uint64_t> revisions;
    std::shared_ptr<CastError> error;
  };

  bool write(const v1::WatchRequest& request) {
    // gRPC allows one writer at a time on a stream (reads run concurrently).
    std::lock_guard<std::mutex> lock(writeMu_);
    return stream_->Write(request);
  }

  // Called with mu_ held.
  void resolve(std::uint32_t watchId, std::map<std::string, std::uint64_t> revisions,
               std::shared_ptr<CastError> error) {
    auto it = pending_.find(watchId);
    if (it == pending_.end()) return;
    it->second->done = true;
    it->second->revisions = std::move(revisions);
    it->second->error = std::move(error);
    pending_.erase(it);
    cv_.notify_all();
  }

  void readLoop() {
    v1::WatchResponse response;
    while (stream_->Read(&response)) {
      // Events first: a created/failed in the same message refers to a
      // watch that has not matched anything yet.
      for (const auto& event : response.events()) {
        std::vector<std::uint32_t> ids(event.watch_ids().begin(), event.watch_ids().end());
        sink_(eventFromPb(event), ids);
      }
      std::lock_guard<std::mutex> lock(mu_);
      if (response.has_created()) {
        std::map<std::string, std::uint64_t> revisions(response.created().revisions().begin(),
                                                      response.created().revisions().end());
        resolve(response.created().watch_id(), std::move(revisions), nullptr);
      }
      if (response.has_failed()) {
        resolve(response.failed().watch_id(), {},
                errorForCode(response.failed().code(), response.failed().message()));
      }
    }
    const grpc::Status status = stream_->Finish();
    std::shared_ptr<CastError> error;
    if (closed_) {
      error = std::make_shared<CastError>("the component closed its connection", "CANCELLED");
    } else if (status.ok()) {
      error = std::make_shared<UnavailableError>("the server at " + endpoint_ + " ended the watch stream");
    } else {
      error = errorForStatus(status);
    }
    {
      std::lock_guard<std::mutex> lock(mu_);
      dead_ = true;
      deathError_ = error;
      while (!pending_.empty()) resolve(pending_.begin()->first, {}, error);
    }
    if (!closed_) onError_(error);
  }

  std::string endpoint_;
  EventSink sink_;
  ErrorSink onError_;
  grpc::ClientContext context_;
  std::unique_ptr<grpc::ClientReaderWriter<v1::WatchRequest, v1::WatchResponse>> stream_;
  std::mutex writeMu_;
  std::mutex mu_;
  std::condition_variable cv_;
  std::map<std::uint32_t, std::shared_ptr<Pending>> pending_;
  bool dead_ = false;
  std::shared_ptr<CastError> deathError_;
  std::atomic<bool> closed_{false};
  std::thread reader_;
};

// ------------------------------------------------------------ the transport

class GrpcTransport final : public Transport {
 public:
  GrpcTransport(const std::string& endpoint, const std::string& token, Identity identity, Millis callTimeout)
      : identity_(std::move(identity)),
        authorization_("Bearer " + token),
        timeout_(callTimeout),
        log_("cast.client." + identity_.componentId) {
    auto directory = std::make_unique<Server>(endpoint);
    directory_ = directory.get();
    servers_[endpoint] = std::move(directory);
    describe();
  }

  ~GrpcTransport() override { close(); }

  const Identity& identity() const override { return identity_; }

  // ---------------------------------------------------------------- writes

  WriteResult add(const std::string& sa, const std::string& id, const std::string& type,
                  const std::string& data) override {
    v1::AddRequest req;
    *req.mutable_address() = addressPb(sa, id);
    setAny(req.mutable_value(), type, data);
    Server& s = server(sa);
    return writeResult(call<v1::WriteResponse>([&](auto* ctx, auto* resp) { return s.wm->Add(ctx, req, resp); }));
  }

  WriteResult overwrite(const std::string& sa, const std::string& id, const std::string& type,
                        const std::string& data, std::optional<std::uint64_t> expectedVersion) override {
    v1::OverwriteRequest req;
    *req.mutable_address() = addressPb(sa, id);
    setAny(req.mutable_value(), type, data);
    if (expectedVersion) req.set_expected_version(*expectedVersion);
    Server& s = server(sa);
    return writeResult(
        call<v1::WriteResponse>([&](auto* ctx, auto* resp) { return s.wm->Overwrite(ctx, req, resp); }));
  }

  WriteResult deleteEntry(const std::string& sa, const std::string& id,
                          std::optional<std::uint64_t> expectedVersion) override {
    v1::DeleteRequest req;
    *req.mutable_address() = addressPb(sa, id);
    if (expectedVersion) req.set_expected_version(*expectedVersion);
    Server& s = server(sa);
    return writeResult(call<v1::WriteResponse>([&](auto* ctx, auto* resp) { return s.wm->Delete(ctx, req, resp); }));
  }

  std::vector<WriteResult> batch(const std::vector<BatchOp>& ops) override {
    if (ops.empty()) return {};
    v1::BatchRequest req;
    for (const auto& op : ops) {
      auto* item = req.add_operations();
      if (op.operation == Operation::Add) {
        auto* add = item->mutable_add();
        *add->mutable_address() = addressPb(op.subarchitecture, op.id);
        setAny(add->mutable_value(), op.type, op.data);
      } else if (op.operation == Operation::Overwrite) {
        auto* ow = item->mutable_overwrite();
        *ow->mutable_address() = addressPb(op.subarchitecture, op.id);
        setAny(ow->mutable_value(), op.type, op.data);
        if (op.expectedVersion) ow->set_expected_version(*op.expectedVersion);
      } else {
        auto* del = item->mutable_delete_();
        *del->mutable_address() = addressPb(op.subarchitecture, op.id);
        if (op.expectedVersion) del->set_expected_version(*op.expectedVersion);
      }
    }
    // A batch is applied by one server: the one of its first operation's SA.
    Server& s = server(ops.front().subarchitecture);
    auto resp = call<v1::BatchResponse>([&](auto* ctx, auto* r) { return s.wm->Batch(ctx, req, r); });
    std::vector<WriteResult> out;
    for (const auto& r : resp.results()) out.push_back(writeResult(r));
    return out;
  }

  // ---------------------------------------------------------------- reads

  EntryRecord get(const std::string& sa, const std::string& id) override {
    v1::GetRequest req;
    *req.mutable_address() = addressPb(sa, id);
    Server& s = server(sa);
    return entryFromPb(call<v1::GetResponse>([&](auto* ctx, auto* r) { return s.wm->Get(ctx, req, r); }).entry());
  }

  std::vector<EntryRecord> getByType(const std::string& sa, const std::string& type, std::uint32_t limit) override {
    v1::GetByTypeRequest req;
    req.set_subarchitecture(sa);
    req.set_type(type);
    req.set_limit(limit);
    Server& s = server(sa);
    auto resp = call<v1::GetByTypeResponse>([&](auto* ctx, auto* r) { return s.wm->GetByType(ctx, req, r); });
    std::vector<EntryRecord> out;
    out.reserve(static_cast<std::size_t>(resp.entries_size()));
    for (const auto& e : resp.entries()) out.push_back(entryFromPb(e));
    return out;
  }

  bool exists(const std::string& sa, const std::string& id) override {
    v1::ExistsRequest req;
    *req.mutable_address() = addressPb(sa, id);
    Server& s = server(sa);
    return call<v1::ExistsResponse>([&](auto* ctx, auto* r) { return s.wm->Exists(ctx, req, r); }).exists();
  }

  // ---------------------------------------------------------------- locks

  std::uint32_t lock(const std::string& sa, const std::string& id, LockMode mode, std::optional<Millis> timeout,
                     bool noWait) override {
    v1::LockRequest req;
    *req.mutable_address() = addressPb(sa, id);
    req.set_mode(static_cast<v1::LockMode>(mode));
    req.set_no_wait(noWait);
    Server& s = server(sa);
    // A blocking lock waits up to the call's deadline: the caller's timeout,
    // or none at all (wait forever), never the default call timeout.
    std::optional<Millis> deadline = noWait ? std::optional<Millis>(timeout_) : timeout;
    return call<v1::LockResponse>([&](auto* ctx, auto* r) { return s.wm->Lock(ctx, req, r); }, deadline).depth();
  }

  std::uint32_t unlock(const std::string& sa, const std::string& id) override {
    v1::UnlockRequest req;
    *req.mutable_address() = addressPb(sa, id);
    Server& s = server(sa);
    return call<v1::UnlockResponse>([&](auto* ctx, auto* r) { return s.wm->Unlock(ctx, req, r); }).depth();
  }

  // ---------------------------------------------------------------- schemas

  void registerSchemas(const google::protobuf::FileDescriptorSet& files) override {
    v1::RegisterSchemasRequest req;
    *req.mutable_files() = files;
    for (Server* s : allServers()) {
      call<v1::RegisterSchemasResponse>([&](auto* ctx, auto* r) { return s->dir->RegisterSchemas(ctx, req, r); });
    }
  }

  // ---------------------------------------------------------------- watching

  void setEventSink(EventSink sink, ErrorSink onError) override {
    std::lock_guard<std::mutex> lock(mu_);
    sink_ = std::move(sink);
    onError_ = std::move(onError);
  }

  std::map<std::string, std::uint64_t> watch(std::uint32_t watchId, const std::vector<ChangeFilter>& filters,
                                             const std::map<std::string, std::uint64_t>& startRevisions) override {
    // A filter naming an SA goes to that SA's server; one with no SA matches
    // every SA, so it goes to every server.
    std::vector<Server*> targets;
    for (const auto& f : filters) {
      std::vector<Server*> servers = f.subarchitecture.empty() ? allServers() : std::vector<Server*>{&server(f.subarchitecture)};
      for (Server* s : servers) {
        if (std::find(targets.begin(), targets.end(), s) == targets.end()) targets.push_back(s);
      }
    }
    std::map<std::string, std::uint64_t> revisions;
    std::vector<std::pair<Server*, std::shared_ptr<WatchStream>>> created;
    try {
      for (Server* s : targets) {
        std::shared_ptr<WatchStream> stream;
        {
          std::lock_guard<std::mutex> lock(mu_);
          if (closing_) throw CastError("the connection is closed", "CANCELLED");
          if (!sink_) throw CastError("setEventSink must be called before watch", "FAILED_PRECONDITION");
          // A stream that ended (server restart, history expired) is
          // replaced, so a component that resynchronises can watch again.
          if (!s->watch || s->watch->dead()) {
            s->watch = std::make_shared<WatchStream>(*s, authorization_, sink_, onError_);
          }
          stream = s->watch;
        }
        std::map<std::string, std::uint64_t> mine;
        for (const auto& kv : startRevisions) {
          if (&server(kv.first) == s) mine.insert(kv);
        }
        auto got = stream->create(watchId, filters, mine, timeout_);
        revisions.insert(got.begin(), got.end());
        created.emplace_back(s, stream);
      }
    } catch (...) {
      // All or nothing: a watch that failed on one server is removed from
      // the others, so no callback receives half of what it asked for.
      for (auto& [s, stream] : created) stream->cancel(watchId);
      throw;
    }
    std::lock_guard<std::mutex> lock(mu_);
    watchStreams_[watchId] = std::move(created);
    return revisions;
  }

  void cancelWatch(std::uint32_t watchId) override {
    std::vector<std::pair<Server*, std::shared_ptr<WatchStream>>> streams;
    {
      std::lock_guard<std::mutex> lock(mu_);
      auto it = watchStreams_.find(watchId);
      if (it == watchStreams_.end()) return;
      streams = std::move(it->second);
      watchStreams_.erase(it);
    }
    for (auto& [s, stream] : streams) stream->cancel(watchId);
  }

  // ---------------------------------------------------------------- tasks

  TaskRecord propose(const std::string& name, const std::string& dataType, const std::string& data,
                     std::int32_t priority) override {
    v1::ProposeRequest req;
    req.set_name(name);
    req.set_priority(priority);
    if (!dataType.empty()) setAny(req.mutable_data(), dataType, data);
    Server& s = server(identity_.subarchitecture);
    return taskFromPb(call<v1::ProposeResponse>([&](auto* ctx, auto* r) { return s.tm->Propose(ctx, req, r); }).task());
  }

  void retract(const std::string& taskId) override {
    v1::RetractRequest req;
    req.set_task_id(taskId);
    Server& s = server(identity_.subarchitecture);
    call<v1::RetractResponse>([&](auto* ctx, auto* r) { return s.tm->Retract(ctx, req, r); });
  }

  void complete(const std::string& taskId, TaskOutcome outcome, const std::string& reason) override {
    v1::CompleteRequest req;
    req.set_task_id(taskId);
    req.set_outcome(static_cast<v1::TaskOutcome>(outcome));
    req.set_reason(reason);
    Server& s = server(identity_.subarchitecture);
    call<v1::CompleteResponse>([&](auto* ctx, auto* r) { return s.tm->Complete(ctx, req, r); });
  }

  void setDecisionSink(DecisionSink sink) override {
    Server& s = server(identity_.subarchitecture);
    std::lock_guard<std::mutex> lock(mu_);
    if (decisions_.joinable()) throw CastError("the decision stream is already open", "FAILED_PRECONDITION");
    decisionContext_ = std::make_unique<grpc::ClientContext>();
    decisionContext_->AddMetadata("authorization", authorization_);
    auto reader = s.tm->Decisions(decisionContext_.get(), v1::DecisionsRequest());
    decisions_ = std::thread([this, sink = std::move(sink), reader = std::move(reader)] {
      v1::Task task;
      while (reader->Read(&task)) sink(taskFromPb(task));
      const grpc::Status status = reader->Finish();
      if (closing_) return;
      auto error = status.ok() ? std::make_shared<UnavailableError>("the task manager ended the decision stream")
                               : errorForStatus(status);
      log_.error(std::string("task decisions stopped: ") + error->name() + ": " + error->message());
      ErrorSink onError;
      {
        std::lock_guard<std::mutex> l(mu_);
        onError = onError_;
      }
      if (onError) onError(error);
    });
  }

  // ---------------------------------------------------------------- sessions

  void startSession(const std::string& language, const std::string& kind, StateSource state) override {
    char host[256] = {0};
    ::gethostname(host, sizeof host - 1);
    for (Server* s : allServers()) {
      v1::RegisterRequest req;
      req.set_language(language);
      req.set_kind(kind);
      req.set_pid(static_cast<std::int64_t>(::getpid()));
      req.set_host(host);
      auto resp = call<v1::RegisterResponse>([&](auto* ctx, auto* r) { return s->dir->Register(ctx, req, r); });
      s->sessionId = resp.session_id();
      const Millis interval(std::max<std::int64_t>(50, resp.lease_ms() / 3));
      s->heartbeatContext = std::make_unique<grpc::ClientContext>();
      s->heartbeatContext->AddMetadata("authorization", authorization_);
      s->heartbeat = std::thread([this, s, interval, state] { heartbeatLoop(*s, interval, state); });
    }
  }

  void stateChanged() override {
    {
      std::lock_guard<std::mutex> lock(mu_);
      ++stateVersion_;
    }
    closingCv_.notify_all();
  }

  void close() override {
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (closing_) return;
      closing_ = true;
    }
    closingCv_.notify_all();
    std::vector<std::shared_ptr<WatchStream>> streams;
    {
      std::lock_guard<std::mutex> lock(mu_);
      for (auto& kv : servers_) {
        if (kv.second->watch) streams.push_back(kv.second->watch);
      }
    }
    for (auto& stream : streams) stream->close();
    if (decisionContext_) decisionContext_->TryCancel();
    if (decisions_.joinable()) decisions_.join();
    // Ending the heartbeat streams ends the sessions: the server releases
    // this component's locks and tasks at once rather than at lease expiry.
    for (auto& kv : servers_) {
      if (kv.second->heartbeatContext) kv.second->heartbeatContext->TryCancel();
      if (kv.second->heartbeat.joinable()) kv.second->heartbeat.join();
    }
  }

 private:
  // One unary call with the token and a deadline (nullopt: none); a failed
  // status becomes the named error.
  template <class Resp, class Fn>
  Resp call(Fn&& fn, std::optional<Millis> deadline) {
    grpc::ClientContext ctx;
    ctx.AddMetadata("authorization", authorization_);
    if (deadline) ctx.set_deadline(std::chrono::system_clock::now() + *deadline);
    Resp resp;
    throwIfError(fn(&ctx, &resp));
    return resp;
  }
  template <class Resp, class Fn>
  Resp call(Fn&& fn) {
    return call<Resp>(std::forward<Fn>(fn), std::optional<Millis>(timeout_));
  }

  void describe() {
    v1::DescribeSystemRequest req;
    Server* d = directory_;
    auto desc = call<v1::SystemDescription>([&](auto* ctx, auto* r) { return d->dir->DescribeSystem(ctx, req, r); });
    std::lock_guard<std::mutex> lock(mu_);
    for (const auto& sa : desc.subarchitectures()) {
      // The directory's own SAs (same endpoint, or none given) reuse its
      // channel: the advertised address may not be the one we dialled.
      if (sa.endpoint().empty() || sa.endpoint() == desc.endpoint()) {
        routes_[sa.name()] = directory_;
      } else {
        auto& slot = servers_[sa.endpoint()];
        if (!slot) slot = std::make_unique<Server>(sa.endpoint());
        routes_[sa.name()] = slot.get();
      }
    }
  }

  // An SA the directory does not know goes to the directory's server, which
  // answers NOT_FOUND naming the SAs it knows.
  Server& server(const std::string& sa) {
    std::lock_guard<std::mutex> lock(mu_);
    auto it = routes_.find(sa);
    return it == routes_.end() ? *directory_ : *it->second;
  }

  std::vector<Server*> allServers() {
    std::lock_guard<std::mutex> lock(mu_);
    std::vector<Server*> out;
    for (auto& kv : servers_) out.push_back(kv.second.get());
    return out;
  }

  void heartbeatLoop(Server& s, Millis interval, const StateSource& state) {
    auto stream = s.dir->Heartbeat(s.heartbeatContext.get());
    v1::HeartbeatResponse response;
    std::uint64_t reported = 0;
    for (;;) {
      {
        std::lock_guard<std::mutex> lock(mu_);
        reported = stateVersion_;
      }
      v1::HeartbeatRequest beat;
      beat.set_session_id(s.sessionId);
      beat.set_state(static_cast<v1::ComponentState>(state()));
      if (!stream->Write(beat) || !stream->Read(&response)) break;
      std::unique_lock<std::mutex> lock(mu_);
      // Wake early for a state change, so it is reported at once.
      closingCv_.wait_for(lock, interval, [&] { return closing_ || stateVersion_ != reported; });
      if (closing_) break;
    }
    s.heartbeatContext->TryCancel();
    const grpc::Status status = stream->Finish();
    bool closing;
    {
      std::lock_guard<std::mutex> lock(mu_);
      closing = closing_;
    }
    if (!closing) {
      // The session is over: the server has released this component's locks
      // and tasks. Say so loudly; the orchestrator restarts the component.
      log_.error("heartbeat to " + s.endpoint + " ended (" + statusCodeName(status.error_code()) + ": " +
                 status.error_message() + "): the session and its locks and tasks are gone");
    }
  }

  Identity identity_;
  std::string authorization_;
  Millis timeout_;
  Logger log_;
  std::mutex mu_;
  std::condition_variable closingCv_;
  bool closing_ = false;
  std::uint64_t stateVersion_ = 0;  // bumped by stateChanged()
  std::map<std::string, std::unique_ptr<Server>> servers_;  // by endpoint
  Server* directory_ = nullptr;
  std::map<std::string, Server*> routes_;  // SA -> server
  std::map<std::uint32_t, std::vector<std::pair<Server*, std::shared_ptr<WatchStream>>>> watchStreams_;
  EventSink sink_;
  ErrorSink onError_;
  std::unique_ptr<grpc::ClientContext> decisionContext_;
  std::thread decisions_;
};

}  // namespace
}  // namespace detail

std::shared_ptr<detail::Transport> connectGrpc(const std::string& endpoint, const std::string& token,
                                               const Identity& identity, std::chrono::milliseconds callTimeout) {
  return std::make_shared<detail::GrpcTransport>(endpoint, token, identity, callTimeout);
}

}  // namespace cast
