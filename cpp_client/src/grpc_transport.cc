// The gRPC transport (cast/grpc_transport.h): routing by SA and the unary
// calls, docs/client-protocol.md call by call. The streams it keeps open live
// beside it: write_stream.cc (Write: every write and lock), watch_stream.cc
// (Watch), session.cc (Register and Heartbeat, and the start barrier's
// AwaitRun); the decision stream is here, being one loop. Large values go by
// shared memory with a server on this host (shm.cc, shm_session.cc): staged
// here for writes, claimed by conversions.cc for reads and events.
// Mirrors the Python client's client/grpc_transport.py.
#include "cast/grpc_transport.h"

#include <algorithm>
#include <map>
#include <mutex>
#include <thread>
#include <vector>

#include "backoff.h"
#include "cast/log.h"
#include "conversions.h"
#include "grpc_server.h"
#include "loan_state.h"
#include "session.h"
#include "watch_stream.h"
#include "write_stream.h"

namespace cast {
namespace detail {
namespace {

// How much longer than a lock's own timeout the client waits for the server's
// answer to it (the server gives up the wait itself; this covers the trip).
// How much longer than a blocking lock's own timeout the client waits for the
// server's answer: the server ends the wait itself at the timeout, the margin
// is the answer's way back (docs/client-protocol.md, "Deadlines").
constexpr Millis kLockReplyMargin{1000};
// How long asking a server where its shared memory is may take: it is asked
// on the way of a write, a read or a watch.
constexpr Millis kDescribeShared{5000};

// What is left of one call's timeout: opening the shared-memory session on
// the call's way (the first large write, or a read) spends from it, so that
// a hung server holds the call for its timeout, not for the opening's
// bounds and then the timeout again.
class Budget {
 public:
  explicit Budget(Millis timeout) : end_(std::chrono::steady_clock::now() + timeout) {}
  // The time left; DeadlineExceededError once there is none (nothing was sent).
  Millis left() const {
    const auto left = std::chrono::duration_cast<Millis>(end_ - std::chrono::steady_clock::now());
    if (left.count() <= 0) {
      throw DeadlineExceededError(
          "the call's deadline passed while opening shared memory with the server: nothing was sent; the server "
          "may be hung or overloaded, retry later");
    }
    return left;
  }

 private:
  std::chrono::steady_clock::time_point end_;
};

class GrpcTransport final : public Transport {
 public:
  GrpcTransport(const std::string& endpoint, const std::string& token, Identity identity,
                const TransportOptions& options)
      : identity_(std::move(identity)),
        tokens_(std::make_shared<TokenSource>(token, options.tokenFile)),
        tls_(options.tls),
        timeout_(options.callTimeout),
        log_("cast.client." + identity_.componentId),
        session_(tokens_, timeout_, log_) {
    auto directory = std::make_unique<Server>(endpoint, tls_);
    directory_ = directory.get();
    attachShared(*directory_);
    servers_[endpoint] = std::move(directory);
    // The directory's server said where its shared memory is: the session
    // with it opens now, so that no call waits for it later.
    directory_->shared->open(describe());
  }

  ~GrpcTransport() override { close(); }

  const Identity& identity() const override { return identity_; }

  // ---------------------------------------------------------------- writes
  // Every write and lock goes on the Write stream of its SA's server
  // (write_stream.cc); reads, tasks and the rest are unary calls.

  // A large value opens the session on the write's way if there is none
  // yet: within the write's own time (Budget).

  WriteResult add(const std::string& sa, const std::string& id, const std::string& type,
                  const std::string& data) override {
    return writeOne(sa, data, [&](const std::string& bytes) { return addRequest(sa, id, type, bytes); });
  }

  WriteResult overwrite(const std::string& sa, const std::string& id, const std::string& type,
                        const std::string& data, std::optional<std::uint64_t> expectedVersion) override {
    return writeOne(sa, data, [&](const std::string& bytes) {
      return overwriteRequest(sa, id, type, bytes, expectedVersion);
    });
  }

  // A message large enough for shared memory is serialised straight into the
  // staging area (stagedMessage): no bytes of it in between.

  WriteResult addMessage(const std::string& sa, const std::string& id, const std::string& type,
                         const google::protobuf::Message& value) override {
    return writeOne(sa, value, [&](const std::string& bytes) { return addRequest(sa, id, type, bytes); });
  }

  WriteResult overwriteMessage(const std::string& sa, const std::string& id, const std::string& type,
                               const google::protobuf::Message& value,
                               std::optional<std::uint64_t> expectedVersion) override {
    return writeOne(sa, value, [&](const std::string& bytes) {
      return overwriteRequest(sa, id, type, bytes, expectedVersion);
    });
  }

  std::future<WriteResult> addMessageAsync(const std::string& sa, const std::string& id, const std::string& type,
                                           const google::protobuf::Message& value) override {
    return writeOneAsync(sa, value, [&](const std::string& bytes) { return addRequest(sa, id, type, bytes); });
  }

  std::future<WriteResult> overwriteMessageAsync(const std::string& sa, const std::string& id,
                                                 const std::string& type, const google::protobuf::Message& value,
                                                 std::optional<std::uint64_t> expectedVersion) override {
    return writeOneAsync(sa, value, [&](const std::string& bytes) {
      return overwriteRequest(sa, id, type, bytes, expectedVersion);
    });
  }

  std::future<WriteResult> addAsync(const std::string& sa, const std::string& id, const std::string& type,
                                    const std::string& data) override {
    return writeOneAsync(sa, data, [&](const std::string& bytes) { return addRequest(sa, id, type, bytes); });
  }

  std::future<WriteResult> overwriteAsync(const std::string& sa, const std::string& id, const std::string& type,
                                          const std::string& data,
                                          std::optional<std::uint64_t> expectedVersion) override {
    return writeOneAsync(sa, data, [&](const std::string& bytes) {
      return overwriteRequest(sa, id, type, bytes, expectedVersion);
    });
  }

  // A loan is placed in the session with its SA's server (placeLoan), opened
  // on the way within the call timeout; its write names its region when it
  // goes on that session still (loanedWrite), else sends its bytes.

  std::unique_ptr<LoanState> loan(const std::string& sa, std::string header, std::size_t size) override {
    const Budget budget(timeout_);
    return placeLoan(*server(sa).shared, std::move(header), size, budget.left());
  }

  WriteResult addLoan(const std::string& sa, const std::string& id, const std::string& type,
                      LoanState& loan) override {
    return writeOne(sa, loan, [&](const std::string& bytes) { return addRequest(sa, id, type, bytes); });
  }

  WriteResult overwriteLoan(const std::string& sa, const std::string& id, const std::string& type, LoanState& loan,
                            std::optional<std::uint64_t> expectedVersion) override {
    return writeOne(sa, loan, [&](const std::string& bytes) {
      return overwriteRequest(sa, id, type, bytes, expectedVersion);
    });
  }

  std::future<WriteResult> addLoanAsync(const std::string& sa, const std::string& id, const std::string& type,
                                        LoanState& loan) override {
    return writeOneAsync(sa, loan, [&](const std::string& bytes) { return addRequest(sa, id, type, bytes); });
  }

  std::future<WriteResult> overwriteLoanAsync(const std::string& sa, const std::string& id,
                                              const std::string& type, LoanState& loan,
                                              std::optional<std::uint64_t> expectedVersion) override {
    return writeOneAsync(sa, loan, [&](const std::string& bytes) {
      return overwriteRequest(sa, id, type, bytes, expectedVersion);
    });
  }

  WriteResult deleteEntry(const std::string& sa, const std::string& id,
                          std::optional<std::uint64_t> expectedVersion) override {
    return writeResult(write(sa, deleteRequest(sa, id, expectedVersion)).write());
  }

  std::vector<WriteResult> batch(const std::vector<BatchOp>& ops) override {
    if (ops.empty()) return {};
    // A batch is applied by one server: the one of its first operation's SA;
    // its large values are staged in the session with that server.
    const std::string& target = ops.front().subarchitecture;
    const Budget budget(timeout_);
    Staging staged;
    v1::WriteRequest request = stagedBatch(*server(target).shared, ops, staged, budget.left());
    v1::WriteReply reply = write(target, std::move(request), staged, budget);
    std::vector<WriteResult> out;
    for (const auto& r : reply.batch().results()) out.push_back(writeResult(r));
    return out;
  }

  // ---------------------------------------------------------------- reads

  // A read on the server's host asks to be lent its large values (shm.h):
  // its metadata names the session and the call, and the call's end says
  // what it received. Opening the session on its way spends its time (Budget).

  // A get with a session goes on its socket when the server answers gets
  // there (SharedMemoryInfo.reads): a frame each way, in order with the
  // component's writes; otherwise, or when that cannot be, the unary call.
  EntryRecord get(const std::string& sa, const std::string& id) override {
    Server& s = server(sa);
    const Budget budget(timeout_);
    // With the token in force now: a read on the socket carries the session's identity, as a write does.
    std::unique_ptr<ReadCall> read = s.shared->read(budget.left(), true);
    if (read && read->session()->reads()) {
      if (std::optional<v1::GetResponse> resp = getOnSocket(sa, id, *read, budget)) {
        EntryRecord record = entryFromPb(resp->entry(), read.get());
        read->end(true);
        return record;
      }
    }
    v1::GetRequest req;
    *req.mutable_address() = addressPb(sa, id);
    auto resp = call<v1::GetResponse>(
        [&](auto* ctx, auto* r) {
          if (read) ctx->AddMetadata(kSharedMemoryMetadata, read->metadata());
          return s.wm->Get(ctx, req, r);
        },
        std::optional<Millis>(budget.left()));
    EntryRecord record = entryFromPb(resp.entry(), read.get());
    if (read) read->end(true);
    return record;
  }

  // A get as a WriteRequest on the socket of `read`'s session, its large
  // value lent on `read` (the SEGMENT frame comes before the reply); nullopt
  // when the unary call must read instead: the session ended (before the get
  // was sent or before its reply: a read changes nothing, so it is made
  // again), or refused its token (it expired; the unary call carries the
  // renewed one).
  std::optional<v1::GetResponse> getOnSocket(const std::string& sa, const std::string& id, ReadCall& read,
                                             const Budget& budget) {
    v1::WriteRequest request;
    request.set_read_call(read.number());
    *request.mutable_get()->mutable_address() = addressPb(sa, id);
    try {
      std::optional<v1::WriteReply> reply = writeStream(sa).read(*read.session(), std::move(request), budget.left());
      if (reply) return std::move(*reply->mutable_get());
    } catch (const UnauthenticatedError&) {
      // The unary call below reads the token again.
    } catch (const UnavailableError&) {
      // The session ended under the get: the unary call below reads instead.
    }
    return std::nullopt;
  }

  std::vector<EntryRecord> getByType(const std::string& sa, const std::string& type, std::uint32_t limit) override {
    v1::GetByTypeRequest req;
    req.set_subarchitecture(sa);
    req.set_type(type);
    req.set_limit(limit);
    Server& s = server(sa);
    const Budget budget(timeout_);
    std::unique_ptr<ReadCall> read = s.shared->read(budget.left());
    auto resp = call<v1::GetByTypeResponse>(
        [&](auto* ctx, auto* r) {
          if (read) ctx->AddMetadata(kSharedMemoryMetadata, read->metadata());
          return s.wm->GetByType(ctx, req, r);
        },
        std::optional<Millis>(budget.left()));
    std::vector<EntryRecord> out;
    out.reserve(static_cast<std::size_t>(resp.entries_size()));
    for (const auto& e : resp.entries()) out.push_back(entryFromPb(e, read.get()));
    if (read) read->end(true);
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
    // A blocking lock waits up to the caller's timeout, or for ever; the
    // server ends the wait itself (DEADLINE_EXCEEDED), so the client waits a
    // margin longer for that answer. A lock that does not wait is answered
    // at once, within the call timeout.
    std::optional<Millis> wait = noWait ? std::optional<Millis>(timeout_) : timeout;
    if (!noWait && timeout) wait = *timeout + kLockReplyMargin;
    return write(sa, lockRequest(sa, id, mode, noWait, timeout), wait).lock().depth();
  }

  std::uint32_t unlock(const std::string& sa, const std::string& id) override {
    return write(sa, unlockRequest(sa, id)).unlock().depth();
  }

  // ---------------------------------------------------------------- schemas

  void registerSchemas(const google::protobuf::FileDescriptorSet& files, const std::string& sa) override {
    v1::RegisterSchemasRequest req;
    *req.mutable_files() = files;
    Server& s = server(sa);
    call<v1::RegisterSchemasResponse>([&](auto* ctx, auto* r) { return s.dir->RegisterSchemas(ctx, req, r); });
  }

  // ---------------------------------------------------------------- watching

  void setEventSink(EventSink sink, ErrorSink onError) override {
    std::lock_guard<std::mutex> lock(mu_);
    sink_ = std::move(sink);
    onError_ = std::move(onError);
  }

  void setSocketEvents(EventSink now, std::function<bool(std::chrono::milliseconds)> room,
                       AttachSource attach) override {
    std::lock_guard<std::mutex> lock(mu_);
    socketEvents_ = SocketEvents{std::move(now), std::move(room), std::move(attach)};
  }

  std::map<std::string, std::uint64_t> watch(std::uint32_t watchId, const std::vector<ChangeFilter>& filters,
                                             const std::map<std::string, std::uint64_t>& startRevisions,
                                             Delivery delivery) override {
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
          auto& slot = watchByServer_[s];
          if (!slot || slot->dead()) {
            // The dead stream is kept until close(): destroying it here would
            // join its reader thread, possibly from the dispatcher thread
            // that reader is waiting on.
            if (slot) retired_.push_back(slot);
            slot = std::make_shared<WatchStream>(*s, tokens_, sink_, onError_, socketEvents_);
          }
          stream = slot;
        }
        std::map<std::string, std::uint64_t> mine;
        for (const auto& kv : startRevisions) {
          if (&server(kv.first) == s) mine.insert(kv);
        }
        auto got = stream->create(watchId, filters, mine, delivery, timeout_);
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
        authorize(*context, *tokens_);
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
                                 : errorForStatus(status, errorTrailer(context->GetServerTrailingMetadata()));
        if (!transient(error->code())) {
          log_.error(std::string("task decisions stopped: ") + error->name() + ": " + error->message());
          if (onError) onError(error);
          return;
        }
        if (closingEvent_.wait(backoff.next())) return;
      }
    });
  }

  // ---------------------------------------------------------------- outcomes

  // To the own SA's server, as task calls go; `cast stats` merges every server's.
  void report(const std::string& name, double value) override {
    v1::ReportRequest req;
    req.set_name(name);
    req.set_value(value);
    Server& s = server(identity_.subarchitecture);
    call<v1::ReportResponse>([&](auto* ctx, auto* r) { return s.insp->Report(ctx, req, r); });
  }

  // ---------------------------------------------------------------- sessions

  void startSession(const std::string& language, const std::string& kind, StateSource state) override {
    std::vector<Server*> servers = allServers();
    // The directory first: the component learns who it is from the server it dialled.
    std::stable_partition(servers.begin(), servers.end(), [this](Server* s) { return s == directory_; });
    session_.start(servers, language, kind, std::move(state));
  }

  std::optional<Identity> verifiedIdentity() const override { return session_.verifiedIdentity(); }

  void stateChanged() override { session_.stateChanged(); }

  bool awaitRun(const StopWait& stopping) override { return session_.awaitRun(*directory_, stopping); }

  std::shared_ptr<ClientSession> sharedSession(const std::string& sa) override { return server(sa).shared->current(); }

  void close() override {
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (closing_) return;
      closing_ = true;
    }
    closingEvent_.set();
    // Writes first: their outstanding replies come while the session (and
    // with it the component's locks) still lives.
    for (auto& kv : writeStreams_) kv.second->close();
    std::vector<std::shared_ptr<WatchStream>> streams;
    std::shared_ptr<grpc::ClientContext> decisionContext;
    {
      std::lock_guard<std::mutex> lock(mu_);
      streams = retired_;
      for (auto& kv : watchByServer_) {
        if (kv.second) streams.push_back(kv.second);
      }
      decisionContext = decisionContext_;
    }
    for (auto& stream : streams) stream->close();
    if (decisionContext) decisionContext->TryCancel();
    session_.close();
    if (decisions_.joinable()) decisions_.join();
    // Last: values still held (views, changes) stay readable; they are given
    // back with the session's end.
    for (Server* s : allServers()) s->shared->close();
  }

 private:
  // The Write stream of `sa`'s server (one per server, made with the routes).
  WriteStream& writeStream(const std::string& sa) { return *writeStreams_.at(&server(sa)); }

  // One write or lock on the Write stream, waiting up to `wait` for its reply.
  v1::WriteReply write(const std::string& sa, v1::WriteRequest request, std::optional<Millis> wait) {
    return writeStream(sa).call(std::move(request), wait);
  }
  // One write, waiting up to the call timeout, as a unary call would.
  v1::WriteReply write(const std::string& sa, v1::WriteRequest request) {
    return write(sa, std::move(request), std::optional<Millis>(timeout_));
  }
  // What is left of a write's `budget`; when nothing is, its regions are
  // free again (it was not sent) and DeadlineExceededError is thrown.
  static Millis timeLeft(const Budget& budget, const Staging& staged) {
    try {
      return budget.left();
    } catch (const CastError&) {
      unstage(staged, nullptr);
      throw;
    }
  }
  // A write with values staged in shared memory, waiting for what is left of
  // its `budget`: their regions are freed when it is over (unstage).
  v1::WriteReply write(const std::string& sa, v1::WriteRequest request, const Staging& staged, const Budget& budget) {
    const Millis left = timeLeft(budget, staged);
    try {
      v1::WriteReply reply = write(sa, std::move(request), std::optional<Millis>(left));
      unstage(staged, nullptr);
      return reply;
    } catch (const CastError& e) {
      unstage(staged, &e);
      throw;
    } catch (...) {
      const UnavailableError unknown("the write failed while it was sent");
      unstage(staged, &unknown);
      throw;
    }
  }
  using BuildRequest = std::function<v1::WriteRequest(const std::string& bytes)>;

  // A value given as bytes or as its message, staged in the session with its
  // SA's server when it is large (shm.h), in the request `build` makes.
  static v1::WriteRequest stage(SharedLink& link, const std::string& data, Staging& staged,
                                const BuildRequest& build, SharedLink::Within within) {
    return stagedWrite(link, data, staged, build, within);
  }
  static v1::WriteRequest stage(SharedLink& link, const google::protobuf::Message& value, Staging& staged,
                                const BuildRequest& build, SharedLink::Within within) {
    return stagedMessage(link, value, staged, build, within);
  }
  // A loan's value: its region named when it is in the session the write goes on.
  static v1::WriteRequest stage(SharedLink& link, LoanState& loan, Staging& staged, const BuildRequest& build,
                                SharedLink::Within within) {
    return loanedWrite(link, loan, staged, build, within);
  }

  // One add or overwrite (as `build` makes its request), waited for or not.
  // `value`: bytes, a message or a loan (stage()).
  template <typename Value>
  WriteResult writeOne(const std::string& sa, Value& value, const BuildRequest& build) {
    const Budget budget(timeout_);
    Staging staged;
    v1::WriteRequest request = stage(*server(sa).shared, value, staged, build, budget.left());
    return writeResult(write(sa, std::move(request), staged, budget).write());
  }
  template <typename Value>
  std::future<WriteResult> writeOneAsync(const std::string& sa, Value& value, const BuildRequest& build) {
    const Budget budget(timeout_);
    Staging staged;
    v1::WriteRequest request = stage(*server(sa).shared, value, staged, build, budget.left());
    return writeAsync(sa, std::move(request), std::move(staged), budget);
  }

  std::future<WriteResult> writeAsync(const std::string& sa, v1::WriteRequest request, Staging staged,
                                      const Budget& budget) {
    const Millis left = timeLeft(budget, staged);
    WriteStream& stream = writeStream(sa);
    if (staged.empty()) return stream.writeAsync(std::move(request), nullptr, left);
    return stream.writeAsync(
        std::move(request),
        [staged = std::move(staged)](const std::shared_ptr<CastError>& error) { unstage(staged, error.get()); }, left);
  }


  // Shared memory with `s` when on its host (shm.h), opened when first needed.
  void attachShared(Server& s) {
    Server* server = &s;
    s.shared = std::make_shared<SharedLink>(
        s.endpoint, tokens_,
        [this, server](SharedLink::Within within) {
          // The server itself says where its shared memory is: ask it, not the directory.
          const v1::DescribeSystemRequest req;
          const Millis bound = std::min(kDescribeShared, timeout_);
          return call<v1::SystemDescription>(
              [&](auto* ctx, auto* r) { return server->dir->DescribeSystem(ctx, req, r); },
              std::optional<Millis>(within ? std::min(bound, *within) : bound));
        },
        log_);
  }

  // A unary call bounded by `deadline` (nullopt: none).
  template <class Resp, class Fn>
  Resp call(Fn&& fn, std::optional<Millis> deadline) {
    return unaryCall<Resp>(*tokens_, deadline, std::forward<Fn>(fn));
  }
  // A unary call bounded by the call timeout.
  template <class Resp, class Fn>
  Resp call(Fn&& fn) {
    return call<Resp>(std::forward<Fn>(fn), std::optional<Millis>(timeout_));
  }

  // Learns which server serves each SA (Directory.DescribeSystem); the answer.
  v1::SystemDescription describe() {
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
        if (!slot) {
          slot = std::make_unique<Server>(sa.endpoint(), tls_);
          attachShared(*slot);
        }
        routes_[sa.name()] = slot.get();
      }
    }
    // A Write stream per server, opened by its first write.
    for (auto& kv : servers_) writeStreams_[kv.second.get()] = std::make_unique<WriteStream>(*kv.second, tokens_, timeout_);
    return desc;
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

  Identity identity_;
  std::shared_ptr<TokenSource> tokens_;
  std::optional<ClientTls> tls_;
  Millis timeout_;
  Logger log_;
  std::mutex mu_;
  bool closing_ = false;  // guarded by mu_; closingEvent_ is the same, for interruptible waits
  Closing closingEvent_;
  std::map<std::string, std::unique_ptr<Server>> servers_;  // by endpoint
  Server* directory_ = nullptr;
  std::map<std::string, Server*> routes_;  // SA -> server
  std::map<Server*, std::unique_ptr<WriteStream>> writeStreams_;  // one per server, fixed after describe()
  std::map<Server*, std::shared_ptr<WatchStream>> watchByServer_;  // the one open stream per server
  std::map<std::uint32_t, std::vector<std::pair<Server*, std::shared_ptr<WatchStream>>>> watchStreams_;
  std::vector<std::shared_ptr<WatchStream>> retired_;  // dead streams, closed by close()
  EventSink sink_;
  ErrorSink onError_;
  SocketEvents socketEvents_;  // unset: every watch's events come on its call
  std::shared_ptr<grpc::ClientContext> decisionContext_;
  std::thread decisions_;
  Session session_;  // last: destroyed (and closed) first, while what it uses still exists
};

}  // namespace

Server::Server(std::string ep, const std::optional<ClientTls>& tls) : endpoint(std::move(ep)) {
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
  std::shared_ptr<grpc::ChannelCredentials> credentials = channelCredentials(tls, args);
  channel = grpc::CreateCustomChannel(endpoint, credentials, args);
  wm = v1::WorkingMemory::NewStub(channel);
  tm = v1::TaskManager::NewStub(channel);
  dir = v1::Directory::NewStub(channel);
  insp = v1::Inspection::NewStub(channel);
}

}  // namespace detail

std::shared_ptr<detail::Transport> connectGrpc(const std::string& endpoint, const std::string& token,
                                               const Identity& identity, const TransportOptions& options) {
  return std::make_shared<detail::GrpcTransport>(endpoint, token, identity, options);
}

}  // namespace cast
