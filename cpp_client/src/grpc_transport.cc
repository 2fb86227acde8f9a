// The gRPC transport: docs/client-protocol.md, call by call. Mirrors the
// Python reference client (python/cast/client/grpc_transport.py).
#include "cast/grpc_transport.h"

#include <grpcpp/grpcpp.h>
#include <unistd.h>

#include <sys/stat.h>

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <fstream>
#include <mutex>
#include <random>
#include <sstream>
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

// Errors after which a stream is opened again (the server went away, or the
// connection broke); any other error ends the stream for good and is reported.
bool transient(const std::string& code) {
  return code == "UNAVAILABLE" || code == "UNKNOWN" || code == "INTERNAL" || code == "CANCELLED" ||
         code == "DEADLINE_EXCEEDED" || code == "UNAUTHENTICATED";
}

// Exponential backoff with jitter for reconnecting: 0.1 s doubling to 3 s.
class Backoff {
 public:
  void reset() { next_ = kInitial; }
  Millis next() {
    static thread_local std::mt19937 rng{std::random_device{}()};
    std::uniform_real_distribution<double> jitter(0.8, 1.2);
    const Millis delay(static_cast<std::int64_t>(static_cast<double>(next_.count()) * jitter(rng)));
    next_ = std::min(kMaximum, next_ * 2);
    return delay;
  }

 private:
  static constexpr Millis kInitial{100};
  static constexpr Millis kMaximum{3000};
  Millis next_{kInitial};
};

// Something to wait on that close() interrupts.
class Closing {
 public:
  bool isSet() {
    std::lock_guard<std::mutex> lock(mu_);
    return set_;
  }
  void set() {
    {
      std::lock_guard<std::mutex> lock(mu_);
      set_ = true;
    }
    cv_.notify_all();
  }
  // Waits up to `delay`; true if closing.
  bool wait(Millis delay) {
    std::unique_lock<std::mutex> lock(mu_);
    return cv_.wait_for(lock, delay, [this] { return set_; });
  }

 private:
  std::mutex mu_;
  std::condition_variable cv_;
  bool set_ = false;
};

// ------------------------------------------------------------ one server

class WatchStream;

struct Server {
  Server(std::string ep, const std::optional<ClientTls>& tls) : endpoint(std::move(ep)) {
    grpc::ChannelArguments args;
    args.SetMaxSendMessageSize(kMaxMessageBytes);
    args.SetMaxReceiveMessageSize(kMaxMessageBytes);
    // Keepalive so that a server that vanished (host down, cable pulled) is
    // noticed by the streams, as in the Python client.
    args.SetInt(GRPC_ARG_KEEPALIVE_TIME_MS, 10000);
    args.SetInt(GRPC_ARG_KEEPALIVE_TIMEOUT_MS, 5000);
    args.SetInt(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
    // Try again soon after the server went away (gRPC's default backoff grows
    // to two minutes), so a restarted server is found within seconds.
    args.SetInt(GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS, 100);
    args.SetInt(GRPC_ARG_MIN_RECONNECT_BACKOFF_MS, 100);
    args.SetInt(GRPC_ARG_MAX_RECONNECT_BACKOFF_MS, 2000);
    std::shared_ptr<grpc::ChannelCredentials> credentials = grpc::InsecureChannelCredentials();
    if (tls) {
      grpc::SslCredentialsOptions ssl;
      ssl.pem_root_certs = readTlsFile(tls->ca);
      if (!tls->cert.empty()) {
        ssl.pem_cert_chain = readTlsFile(tls->cert);
        ssl.pem_private_key = readTlsFile(tls->key);
      }
      credentials = grpc::SslCredentials(ssl);
      if (!tls->serverName.empty()) args.SetSslTargetNameOverride(tls->serverName);
    }
    channel = grpc::CreateCustomChannel(endpoint, credentials, args);
    wm = v1::WorkingMemory::NewStub(channel);
    tm = v1::TaskManager::NewStub(channel);
    dir = v1::Directory::NewStub(channel);
  }

  static std::string readTlsFile(const std::string& path) {
    std::ifstream in(path, std::ios::binary);
    if (!in) throw InvalidArgumentError("cannot read a TLS file (CAST_TLS_CA/CERT/KEY): " + path);
    std::ostringstream text;
    text << in.rdbuf();
    return text.str();
  }

  std::string endpoint;
  std::shared_ptr<grpc::Channel> channel;
  std::unique_ptr<v1::WorkingMemory::Stub> wm;
  std::unique_ptr<v1::TaskManager::Stub> tm;
  std::unique_ptr<v1::Directory::Stub> dir;
  std::shared_ptr<WatchStream> watch;  // guarded by GrpcTransport::mu_
  std::string sessionId;               // guarded by GrpcTransport::mu_
  std::shared_ptr<grpc::ClientContext> heartbeatContext;  // guarded by GrpcTransport::mu_
  std::thread heartbeat;
};

// ------------------------------------------------------------ watch stream

// One Watch call to one server, shared by every watch of the component there.
//
// When the connection breaks the stream is opened again with backoff and
// every watch is created again from the revision after the last one it got
// (per SA): no gap and no duplicate. The server's history id goes along, so a
// server that lost that history (restarted without persistence) refuses the
// resume, and the component is told to resynchronise (watchFailed with
// HistoryExpiredError).
class WatchStream {
 public:
  WatchStream(Server& server, std::shared_ptr<TokenSource> tokens, EventSink sink, ErrorSink onError)
      : server_(server), tokens_(std::move(tokens)), sink_(std::move(sink)), onError_(std::move(onError)),
        log_("cast.client.watch") {
    thread_ = std::thread([this] { run(); });
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
      auto w = std::make_shared<Watch>();
      w->watchId = watchId;
      w->filters = filters;
      w->firstStarts = starts;
      watches_[watchId] = w;
      pending_[watchId] = pending;
      // Sent now if a stream is open; otherwise the next open sends it.
      if (stream_) write(createRequest(*w));
    }
    std::unique_lock<std::mutex> lock(mu_);
    if (!cv_.wait_for(lock, timeout, [&] { return pending->done; })) {
      pending_.erase(watchId);
      watches_.erase(watchId);
      if (!connected_) {
        throw UnavailableError("server " + server_.endpoint + " unreachable: the watch was not created within " +
                               std::to_string(timeout.count()) + " ms");
      }
      throw DeadlineExceededError("the server at " + server_.endpoint + " did not confirm watch " +
                                  std::to_string(watchId) + " within " + std::to_string(timeout.count()) + " ms");
    }
    if (pending->error) {
      watches_.erase(watchId);
      pending->error->raise();
    }
    return pending->revisions;
  }

  void cancel(std::uint32_t watchId) {
    std::lock_guard<std::mutex> lock(mu_);
    watches_.erase(watchId);
    if (stream_) {
      v1::WatchRequest request;
      request.mutable_cancel()->set_watch_id(watchId);
      write(request);
    }
  }

  void close() {
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (closed_) return;
      closed_ = true;
      if (context_) context_->TryCancel();
    }
    closing_.set();
    if (thread_.joinable()) thread_.join();
  }

  int reconnects() {
    std::lock_guard<std::mutex> lock(mu_);
    return reconnects_;
  }

 private:
  struct Pending {
    bool done = false;
    std::map<std::string, std::uint64_t> revisions;
    std::shared_ptr<CastError> error;
  };

  // What the client keeps of one watch to create it again after a reconnect.
  struct Watch {
    std::uint32_t watchId = 0;
    std::vector<ChangeFilter> filters;
    std::map<std::string, std::uint64_t> firstStarts;
    std::vector<std::string> sas;  // the SAs of this server the watch covers (known once created)
    // Per SA, the revision the watch is known to have seen up to (unset until created).
    std::optional<std::map<std::string, std::uint64_t>> base;
  };

  // Called with mu_ held.
  v1::WatchRequest createRequest(Watch& w) {
    v1::WatchRequest request;
    auto* create = request.mutable_create();
    create->set_watch_id(w.watchId);
    for (const auto& f : w.filters) filterToPb(f, create->add_filters());
    if (!w.base) {
      for (const auto& kv : w.firstStarts) (*create->mutable_start_revisions())[kv.first] = kv.second;
      return request;
    }
    std::map<std::string, std::uint64_t> base;
    for (const auto& sa : w.sas) {
      const std::uint64_t from = std::max((*w.base)[sa], seen_[sa]) + 1;
      (*create->mutable_start_revisions())[sa] = from;
      // What is sent is where the watch now is: a later resume never goes back before it.
      base[sa] = from - 1;
    }
    w.base = std::move(base);
    create->set_history_id(historyId_);
    return request;
  }

  // Called with mu_ held (so writes never overlap: gRPC allows one writer).
  bool write(const v1::WatchRequest& request) { return stream_ && stream_->Write(request); }

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

  void run() {
    Backoff backoff;
    while (true) {
      std::shared_ptr<grpc::ClientReaderWriter<v1::WatchRequest, v1::WatchResponse>> stream;
      std::shared_ptr<grpc::ClientContext> context;
      {
        std::lock_guard<std::mutex> lock(mu_);
        if (closed_) break;
        context_ = context = std::make_shared<grpc::ClientContext>();
        context->AddMetadata("authorization", "Bearer " + tokens_->token());
      }
      // Opening may wait for the connection: not under mu_, so that close()
      // can cancel it.
      stream = server_.wm->Watch(context.get());
      {
        std::lock_guard<std::mutex> lock(mu_);
        stream_ = stream;
        for (auto& kv : watches_) write(createRequest(*kv.second));
      }
      v1::WatchResponse response;
      while (stream->Read(&response)) {
        if (!connected_) {
          connected_ = true;
          backoff.reset();
        }
        handle(response);
      }
      const grpc::Status status = stream->Finish();
      connected_ = false;
      {
        std::lock_guard<std::mutex> lock(mu_);
        stream_.reset();
        if (closed_) break;
      }
      std::shared_ptr<CastError> error =
          status.ok() ? std::make_shared<UnavailableError>("the watch stream to " + server_.endpoint + " ended")
                      : errorForStatus(status);
      if (!transient(error->code())) {
        fail(error);
        return;
      }
      log_.warning("watch stream to " + server_.endpoint + " broke (" + error->message() + "); reconnecting");
      {
        std::lock_guard<std::mutex> lock(mu_);
        ++reconnects_;
      }
      if (closing_.wait(backoff.next())) break;
    }
    // Closed: creates still waiting learn why.
    std::lock_guard<std::mutex> lock(mu_);
    auto closedError = std::make_shared<CastError>("the component closed its connection", "CANCELLED");
    while (!pending_.empty()) resolve(pending_.begin()->first, {}, closedError);
  }

  void handle(const v1::WatchResponse& response) {
    // Events first: a created/failed in the same message refers to a watch
    // that has not matched anything yet.
    for (const auto& event : response.events()) {
      std::vector<std::uint32_t> ids(event.watch_ids().begin(), event.watch_ids().end());
      EventRecord record = eventFromPb(event);
      const std::string sa = record.address.subarchitecture;
      const std::uint64_t revision = record.revision;
      sink_(std::move(record), ids);
      std::lock_guard<std::mutex> lock(mu_);
      // The server moves every watch of an SA on one stream past the events it
      // sends, so each watch has seen at least this far.
      if (revision > seen_[sa]) seen_[sa] = revision;
    }
    std::shared_ptr<CastError> resumeRefused;
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (response.has_created()) {
        const auto& created = response.created();
        if (!created.history_id().empty()) historyId_ = created.history_id();
        std::map<std::string, std::uint64_t> revisions(created.revisions().begin(), created.revisions().end());
        auto it = watches_.find(created.watch_id());
        if (it != watches_.end() && !it->second->base) {
          Watch& w = *it->second;
          const bool coversAll = std::any_of(w.filters.begin(), w.filters.end(),
                                             [](const ChangeFilter& f) { return f.subarchitecture.empty(); });
          std::map<std::string, std::uint64_t> base;
          for (const auto& [sa, revision] : revisions) {
            const bool mine = coversAll || std::any_of(w.filters.begin(), w.filters.end(),
                                                       [&](const ChangeFilter& f) { return f.subarchitecture == sa; });
            if (!mine) continue;
            w.sas.push_back(sa);
            auto start = w.firstStarts.find(sa);
            base[sa] = (start == w.firstStarts.end() ? revision + 1 : start->second) - 1;
          }
          w.base = std::move(base);
        }
        resolve(created.watch_id(), std::move(revisions), nullptr);
      }
      if (response.has_failed()) {
        const auto& failed = response.failed();
        auto error = errorForCode(failed.code(), failed.message());
        if (pending_.count(failed.watch_id())) {
          resolve(failed.watch_id(), {}, error);
        } else if (watches_.erase(failed.watch_id()) > 0) {
          // A resume refused after a reconnect: the history no longer covers
          // it (or the server lost it): the component must resynchronise.
          if (error->code() != "OUT_OF_RANGE") {
            error = std::make_shared<HistoryExpiredError>("watch " + std::to_string(failed.watch_id()) +
                                                          " could not resume: " + failed.message());
          }
          resumeRefused = error;
        }
      }
    }
    if (resumeRefused) onError_(resumeRefused);
  }

  void fail(const std::shared_ptr<CastError>& error) {
    {
      std::lock_guard<std::mutex> lock(mu_);
      dead_ = true;
      deathError_ = error;
      watches_.clear();
      while (!pending_.empty()) resolve(pending_.begin()->first, {}, error);
    }
    onError_(error);
  }

  Server& server_;
  std::shared_ptr<TokenSource> tokens_;
  EventSink sink_;
  ErrorSink onError_;
  Logger log_;
  std::mutex mu_;
  std::condition_variable cv_;
  std::shared_ptr<grpc::ClientContext> context_;
  std::shared_ptr<grpc::ClientReaderWriter<v1::WatchRequest, v1::WatchResponse>> stream_;
  std::map<std::uint32_t, std::shared_ptr<Watch>> watches_;
  std::map<std::uint32_t, std::shared_ptr<Pending>> pending_;
  std::map<std::string, std::uint64_t> seen_;  // newest revision per SA received on this stream
  std::string historyId_;
  std::atomic<bool> connected_{false};
  bool dead_ = false;
  bool closed_ = false;
  int reconnects_ = 0;
  std::shared_ptr<CastError> deathError_;
  Closing closing_;
  std::thread thread_;
};

// ------------------------------------------------------------ the transport

class GrpcTransport final : public Transport {
 public:
  GrpcTransport(const std::string& endpoint, const std::string& token, Identity identity,
                const TransportOptions& options)
      : identity_(std::move(identity)),
        tokens_(std::make_shared<TokenSource>(token, options.tokenFile)),
        tls_(options.tls),
        timeout_(options.callTimeout),
        log_("cast.client." + identity_.componentId) {
    auto directory = std::make_unique<Server>(endpoint, tls_);
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
            // The dead stream is kept until close(): destroying it here would
            // join its reader thread, possibly from the dispatcher thread
            // that reader is waiting on.
            if (s->watch) retired_.push_back(s->watch);
            s->watch = std::make_shared<WatchStream>(*s, tokens_, sink_, onError_);
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
    // Opened again after a disconnect (the server sends the decisions made
    // meanwhile, as it does on every open).
    decisions_ = std::thread([this, &s, sink = std::move(sink)] {
      Backoff backoff;
      while (true) {
        auto context = std::make_shared<grpc::ClientContext>();
        {
          std::lock_guard<std::mutex> l(mu_);
          if (closing_) return;
          decisionContext_ = context;
        }
        context->AddMetadata("authorization", "Bearer " + tokens_->token());
        auto reader = s.tm->Decisions(context.get(), v1::DecisionsRequest());
        v1::Task task;
        while (reader->Read(&task)) {
          backoff.reset();
          sink(taskFromPb(task));
        }
        const grpc::Status status = reader->Finish();
        ErrorSink onError;
        {
          std::lock_guard<std::mutex> l(mu_);
          if (closing_) return;
          onError = onError_;
        }
        auto error = status.ok() ? std::make_shared<UnavailableError>("the task manager ended the decision stream")
                                 : errorForStatus(status);
        if (!transient(error->code())) {
          log_.error(std::string("task decisions stopped: ") + error->name() + ": " + error->message());
          if (onError) onError(error);
          return;
        }
        if (closingEvent_.wait(backoff.next())) return;
      }
    });
  }

  // ---------------------------------------------------------------- sessions

  void startSession(const std::string& language, const std::string& kind, StateSource state) override {
    for (Server* s : allServers()) {
      const Millis interval = registerWith(*s, language, kind);
      s->heartbeat = std::thread([this, s, interval, language, kind, state] {
        heartbeatLoop(*s, interval, language, kind, state);
      });
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
    closingEvent_.set();
    std::vector<std::shared_ptr<WatchStream>> streams;
    std::vector<std::shared_ptr<grpc::ClientContext>> contexts;
    {
      std::lock_guard<std::mutex> lock(mu_);
      streams = retired_;
      for (auto& kv : servers_) {
        if (kv.second->watch) streams.push_back(kv.second->watch);
        if (kv.second->heartbeatContext) contexts.push_back(kv.second->heartbeatContext);
      }
      if (decisionContext_) contexts.push_back(decisionContext_);
    }
    for (auto& stream : streams) stream->close();
    // Ending the heartbeat streams ends the sessions: the server releases
    // this component's locks and tasks at once rather than at lease expiry.
    for (auto& context : contexts) context->TryCancel();
    if (decisions_.joinable()) decisions_.join();
    for (auto& kv : servers_) {
      if (kv.second->heartbeat.joinable()) kv.second->heartbeat.join();
    }
  }

 private:
  // One unary call with the token and a deadline (nullopt: none); a failed
  // status becomes the named error.
  template <class Resp, class Fn>
  Resp call(Fn&& fn, std::optional<Millis> deadline) {
    for (int attempt = 0;; ++attempt) {
      grpc::ClientContext ctx;
      ctx.AddMetadata("authorization", "Bearer " + tokens_->token());
      if (deadline) ctx.set_deadline(std::chrono::system_clock::now() + *deadline);
      Resp resp;
      const grpc::Status status = fn(&ctx, &resp);
      if (status.ok()) return resp;
      // A refused token may just have been renewed in its file: read it and
      // try once more.
      if (attempt == 0 && status.error_code() == grpc::StatusCode::UNAUTHENTICATED && tokens_->refresh()) continue;
      errorForStatus(status)->raise();
    }
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
        if (!slot) slot = std::make_unique<Server>(sa.endpoint(), tls_);
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

  Millis registerWith(Server& s, const std::string& language, const std::string& kind) {
    char host[256] = {0};
    ::gethostname(host, sizeof host - 1);
    v1::RegisterRequest req;
    req.set_language(language);
    req.set_kind(kind);
    req.set_pid(static_cast<std::int64_t>(::getpid()));
    req.set_host(host);
    auto resp = call<v1::RegisterResponse>([&](auto* ctx, auto* r) { return s.dir->Register(ctx, req, r); });
    std::lock_guard<std::mutex> lock(mu_);
    s.sessionId = resp.session_id();
    ++sessions_;
    return Millis(std::max<std::int64_t>(50, resp.lease_ms() / 3));
  }

  // Keeps one server's session alive; a lost session (server restart, cut
  // connection, lease expiry) is registered again with backoff: a new
  // session, since the server released the old one's locks and tasks.
  void heartbeatLoop(Server& s, Millis interval, const std::string& language, const std::string& kind,
                     const StateSource& state) {
    Backoff backoff;
    while (true) {
      auto context = std::make_shared<grpc::ClientContext>();
      std::string sessionId;
      {
        std::lock_guard<std::mutex> lock(mu_);
        if (closing_) return;
        s.heartbeatContext = context;
        sessionId = s.sessionId;
      }
      context->AddMetadata("authorization", "Bearer " + tokens_->token());
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
        closingCv_.wait_for(lock, interval, [&] { return closing_ || stateVersion_ != reported; });
        if (closing_) break;
      }
      context->TryCancel();
      const grpc::Status status = stream->Finish();
      {
        std::lock_guard<std::mutex> lock(mu_);
        if (closing_) return;
      }
      log_.warning("session with " + s.endpoint + " lost (" + statusCodeName(status.error_code()) + ": " +
                   status.error_message() + "): its locks and tasks are released; registering again");
      while (!closingEvent_.wait(backoff.next())) {
        try {
          interval = registerWith(s, language, kind);
          log_.info("registered again with " + s.endpoint);
          break;
        } catch (const CastError& e) {
          log_.info("registering with " + s.endpoint + " failed (" + e.message() + "); retrying");
        }
      }
    }
  }

  Identity identity_;
  std::shared_ptr<TokenSource> tokens_;
  std::optional<ClientTls> tls_;
  Millis timeout_;
  Logger log_;
  std::mutex mu_;
  std::condition_variable closingCv_;
  bool closing_ = false;  // guarded by mu_; closingEvent_ is the same, for interruptible waits
  Closing closingEvent_;
  std::uint64_t stateVersion_ = 0;  // bumped by stateChanged()
  int sessions_ = 0;                // sessions registered (more than one per server after reconnects)
  std::map<std::string, std::unique_ptr<Server>> servers_;  // by endpoint
  Server* directory_ = nullptr;
  std::map<std::string, Server*> routes_;  // SA -> server
  std::map<std::uint32_t, std::vector<std::pair<Server*, std::shared_ptr<WatchStream>>>> watchStreams_;
  std::vector<std::shared_ptr<WatchStream>> retired_;  // dead streams, closed by close()
  EventSink sink_;
  ErrorSink onError_;
  std::shared_ptr<grpc::ClientContext> decisionContext_;
  std::thread decisions_;
};

}  // namespace
}  // namespace detail

std::shared_ptr<detail::Transport> connectGrpc(const std::string& endpoint, const std::string& token,
                                               const Identity& identity, const TransportOptions& options) {
  return std::make_shared<detail::GrpcTransport>(endpoint, token, identity, options);
}

// ------------------------------------------------------------ TLS, tokens

std::optional<ClientTls> ClientTls::fromEnv(const std::map<std::string, std::string>& env) {
  auto get = [&](const char* name) {
    auto it = env.find(name);
    return it == env.end() ? std::string() : it->second;
  };
  ClientTls tls{get("CAST_TLS_CA"), get("CAST_TLS_CERT"), get("CAST_TLS_KEY"), get("CAST_TLS_SERVER_NAME")};
  if (tls.ca.empty()) {
    if (!tls.cert.empty() || !tls.key.empty()) {
      throw InvalidArgumentError("CAST_TLS_CERT/CAST_TLS_KEY given without CAST_TLS_CA: set the CA too");
    }
    return std::nullopt;
  }
  if (tls.cert.empty() != tls.key.empty()) {
    throw InvalidArgumentError("set both CAST_TLS_CERT and CAST_TLS_KEY, or neither");
  }
  return tls;
}

TokenSource::TokenSource(std::string token, std::string path, std::chrono::milliseconds checkInterval)
    : token_(std::move(token)), path_(std::move(path)), interval_(checkInterval) {
  if (!path_.empty()) reload(true);
}

void TokenSource::reload(bool force) {
  // Called with mu_ held.
  const auto now = std::chrono::steady_clock::now();
  if (!force && now - checked_ < interval_) return;
  checked_ = now;
  struct stat st {};
  if (::stat(path_.c_str(), &st) != 0) return;  // keep the last token: the file may be being replaced
  const std::pair<long long, long long> stamp{
      static_cast<long long>(st.st_mtim.tv_sec) * 1000000000LL + st.st_mtim.tv_nsec,
      static_cast<long long>(st.st_size)};
  if (stamp == stamp_) return;
  std::ifstream in(path_);
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const auto first = text.find_first_not_of(" \t\r\n");
  const auto last = text.find_last_not_of(" \t\r\n");
  if (first != std::string::npos) token_ = text.substr(first, last - first + 1);
  stamp_ = stamp;
}

std::string TokenSource::token() {
  std::lock_guard<std::mutex> lock(mu_);
  if (!path_.empty()) reload(false);
  return token_;
}

bool TokenSource::refresh() {
  if (path_.empty()) return false;
  std::lock_guard<std::mutex> lock(mu_);
  const std::string before = token_;
  reload(true);
  return token_ != before;
}

}  // namespace cast
