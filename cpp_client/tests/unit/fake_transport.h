// An in-memory transport for unit tests: one WM per SA with versions, locks
// of a single holder, change events delivered synchronously, and tasks that
// are adopted at once. It stores bytes, like the server, so tests of the
// component's copy semantics see what a real WM would give back. It is a
// test double for the component logic, not a model of the server: the
// pytest interop tests run the real thing.
#pragma once

#include <algorithm>
#include <map>
#include <mutex>
#include <set>
#include <string>
#include <vector>

#include "loan_state.h"
#include "transport.h"

namespace cast::testing {

class FakeTransport : public detail::Transport {
 public:
  explicit FakeTransport(Identity identity) : identity_(std::move(identity)) {}

  const Identity& identity() const override { return identity_; }

  WriteResult add(const std::string& sa, const std::string& id, const std::string& type,
                  const std::string& data) override {
    std::unique_lock<std::mutex> lock(mu_);
    ++calls["add"];
    auto key = sa + "/" + id;
    if (entries_.count(key)) throw AlreadyExistsError("entry '" + id + "' already exists in " + sa);
    detail::EntryRecord r{{id, sa}, type, data, 0, identity_.componentId, ++revision_, 0};
    entries_[key] = r;
    return emit(lock, Operation::Add, r);
  }

  WriteResult overwrite(const std::string& sa, const std::string& id, const std::string& type,
                        const std::string& data, std::optional<std::uint64_t> expected) override {
    std::unique_lock<std::mutex> lock(mu_);
    ++calls["overwrite"];
    auto it = entries_.find(sa + "/" + id);
    if (it == entries_.end()) throw NotFoundError("no entry '" + id + "' in " + sa);
    if (expected && *expected != it->second.version) throw ConsistencyError("version mismatch");
    if (lockedByOther.count(sa + "/" + id)) throw LockedError("locked by other");
    it->second.type = type;
    it->second.data = data;
    it->second.version += 1;
    it->second.revision = ++revision_;
    return emit(lock, Operation::Overwrite, it->second);
  }

  WriteResult deleteEntry(const std::string& sa, const std::string& id,
                          std::optional<std::uint64_t> expected) override {
    std::unique_lock<std::mutex> lock(mu_);
    ++calls["delete"];
    auto it = entries_.find(sa + "/" + id);
    if (it == entries_.end()) throw NotFoundError("no entry '" + id + "' in " + sa);
    if (expected && *expected != it->second.version) throw ConsistencyError("version mismatch");
    detail::EntryRecord r = it->second;
    r.revision = ++revision_;
    entries_.erase(it);
    locks_.erase(sa + "/" + id);
    return emit(lock, Operation::Delete, r);
  }

  std::vector<WriteResult> batch(const std::vector<detail::BatchOp>& ops) override {
    std::vector<WriteResult> out;
    batches.push_back(ops);
    for (const auto& op : ops) {
      if (op.operation == Operation::Add) out.push_back(add(op.subarchitecture, op.id, op.type, op.data));
      else if (op.operation == Operation::Overwrite)
        out.push_back(overwrite(op.subarchitecture, op.id, op.type, op.data, op.expectedVersion));
      else out.push_back(deleteEntry(op.subarchitecture, op.id, op.expectedVersion));
    }
    return out;
  }

  // A loan is private memory here (no shared memory); its writes send its bytes (Transport's defaults).
  std::unique_ptr<detail::LoanState> loan(const std::string& sa, std::string header, std::size_t size) override {
    {
      std::lock_guard<std::mutex> lock(mu_);
      ++calls["loan"];
    }
    return detail::privateLoan(std::move(header), size);
  }

  detail::EntryRecord get(const std::string& sa, const std::string& id) override {
    std::lock_guard<std::mutex> lock(mu_);
    auto it = entries_.find(sa + "/" + id);
    if (it == entries_.end()) throw NotFoundError("no entry '" + id + "' in " + sa);
    return it->second;
  }

  std::vector<detail::EntryRecord> getByType(const std::string& sa, const std::string& type,
                                             std::uint32_t limit) override {
    std::lock_guard<std::mutex> lock(mu_);
    std::vector<detail::EntryRecord> out;
    for (const auto& kv : entries_) {
      if (kv.second.address.subarchitecture == sa && kv.second.type == type) out.push_back(kv.second);
    }
    std::sort(out.begin(), out.end(), [](const auto& a, const auto& b) { return a.revision > b.revision; });
    if (limit && out.size() > limit) out.resize(limit);
    return out;
  }

  bool exists(const std::string& sa, const std::string& id) override {
    std::lock_guard<std::mutex> lock(mu_);
    return entries_.count(sa + "/" + id) > 0;
  }

  std::uint32_t lock(const std::string& sa, const std::string& id, LockMode mode,
                     std::optional<std::chrono::milliseconds> timeout, bool noWait) override {
    std::lock_guard<std::mutex> lock(mu_);
    lastLockTimeout = timeout;
    lastLockNoWait = noWait;
    lastLockMode = mode;
    const auto key = sa + "/" + id;
    if (lockedByOther.count(key)) {
      if (noWait) throw LockedError("entry '" + id + "' is locked by other");
      throw DeadlineExceededError("Deadline Exceeded");
    }
    return ++locks_[key];
  }

  std::uint32_t unlock(const std::string& sa, const std::string& id) override {
    std::lock_guard<std::mutex> lock(mu_);
    ++calls["unlock"];
    auto it = locks_.find(sa + "/" + id);
    if (it == locks_.end()) throw LockedError("'" + id + "' is not locked by you");
    std::uint32_t left = --it->second;
    if (left == 0) locks_.erase(it);
    return left;
  }

  std::uint32_t lockDepth(const std::string& sa, const std::string& id) {
    std::lock_guard<std::mutex> lock(mu_);
    auto it = locks_.find(sa + "/" + id);
    return it == locks_.end() ? 0 : it->second;
  }

  void registerSchemas(const google::protobuf::FileDescriptorSet& files, const std::string& sa) override {
    std::lock_guard<std::mutex> lock(mu_);
    registered.push_back(files);
    registeredSas.push_back(sa);
  }

  void setEventSink(detail::EventSink sink, detail::ErrorSink onError) override {
    std::lock_guard<std::mutex> lock(mu_);
    sink_ = std::move(sink);
    onError_ = std::move(onError);
  }

  std::map<std::string, std::uint64_t> watch(std::uint32_t watchId, const std::vector<ChangeFilter>& filters,
                                             const std::map<std::string, std::uint64_t>&, Delivery delivery) override {
    std::lock_guard<std::mutex> lock(mu_);
    deliveries[watchId] = delivery;
    if (failNextWatch) {
      failNextWatch = false;
      throw InvalidArgumentError("bad filter");
    }
    watches_[watchId] = filters;
    return {};
  }

  void cancelWatch(std::uint32_t watchId) override {
    std::lock_guard<std::mutex> lock(mu_);
    watches_.erase(watchId);
    cancelled.push_back(watchId);
  }

  // Delivers an event as a server's stream would (conflated ones included).
  void deliver(const detail::EventRecord& event, const std::vector<std::uint32_t>& watchIds) {
    detail::EventSink sink;
    {
      std::lock_guard<std::mutex> lock(mu_);
      sink = sink_;
    }
    sink(event, watchIds);
  }

  // Simulates the watch stream ending with an error.
  void failWatches(std::shared_ptr<CastError> error) {
    detail::ErrorSink onError;
    {
      std::lock_guard<std::mutex> lock(mu_);
      onError = onError_;
    }
    onError(std::move(error));
  }

  detail::TaskRecord propose(const std::string& name, const std::string& dataType, const std::string& data,
                             std::int32_t priority) override {
    detail::TaskRecord t;
    detail::DecisionSink sink;
    {
      std::lock_guard<std::mutex> lock(mu_);
      t.taskId = "task-" + std::to_string(++tasks_);
      t.name = name;
      t.subarchitecture = identity_.subarchitecture;
      t.component = identity_.componentId;
      t.priority = priority;
      t.dataType = dataType;
      t.data = data;
      t.state = TaskState::Waiting;
      sink = decisions_;
    }
    detail::TaskRecord decided = t;
    decided.state = name.rfind("reject", 0) == 0 ? TaskState::Rejected : TaskState::Adopted;
    if (sink) sink(decided);
    return t;
  }

  void retract(const std::string& taskId) override {
    std::lock_guard<std::mutex> lock(mu_);
    retracted.push_back(taskId);
  }

  void complete(const std::string& taskId, TaskOutcome outcome, const std::string& reason) override {
    std::lock_guard<std::mutex> lock(mu_);
    completed.emplace_back(taskId, outcome);
  }

  // Records what was reported; reportError, when set, is thrown instead (a server that refuses).
  void report(const std::string& name, double value) override {
    std::lock_guard<std::mutex> lock(mu_);
    if (reportError) reportError->raise();
    reports.emplace_back(name, value);
  }

  void setDecisionSink(detail::DecisionSink sink) override {
    std::lock_guard<std::mutex> lock(mu_);
    decisions_ = std::move(sink);
  }

  void startSession(const std::string& language, const std::string& kind, detail::StateSource state) override {
    std::lock_guard<std::mutex> lock(mu_);
    sessionLanguage = language;
    sessionKind = kind;
    state_ = std::move(state);
    sessionStarted_ = true;
  }

  // What `verified` says, once the session is registered (as a server answers Register).
  std::optional<Identity> verifiedIdentity() const override {
    std::lock_guard<std::mutex> lock(mu_);
    return sessionStarted_ ? verified : std::nullopt;
  }

  ComponentState reportedState() {
    std::lock_guard<std::mutex> lock(mu_);
    return state_();
  }

  // Every state reported at once through stateChanged(), in order.
  void stateChanged() override {
    std::lock_guard<std::mutex> lock(mu_);
    if (state_) stateChanges.push_back(state_());
  }

  // The start barrier: released unless holdBarrier() was called; waits poll
  // every 5 ms, as a long-poll would, and see a stop request in between.
  bool awaitRun(const detail::StopWait& stopping) override {
    {
      std::lock_guard<std::mutex> lock(mu_);
      ++awaitRunCalls;
      stateAtAwaitRun = state_ ? std::optional<ComponentState>(state_()) : std::nullopt;
      if (awaitRunError) awaitRunError->raise();
    }
    while (!stopping(std::chrono::milliseconds(0))) {
      {
        std::lock_guard<std::mutex> lock(mu_);
        if (!barrierHeld_) return true;
      }
      if (stopping(std::chrono::milliseconds(5))) break;
    }
    return false;
  }
  void holdBarrier() {
    std::lock_guard<std::mutex> lock(mu_);
    barrierHeld_ = true;
  }
  void releaseBarrier() {
    std::lock_guard<std::mutex> lock(mu_);
    barrierHeld_ = false;
  }
  int awaitRunCount() {
    std::lock_guard<std::mutex> lock(mu_);
    return awaitRunCalls;
  }

  void close() override {
    std::lock_guard<std::mutex> lock(mu_);
    closed = true;
  }

  // What the tests inspect.
  std::map<std::string, int> calls;
  std::vector<google::protobuf::FileDescriptorSet> registered;
  std::vector<std::string> registeredSas;  // the SA of each registration
  std::vector<std::vector<detail::BatchOp>> batches;
  std::vector<std::uint32_t> cancelled;
  std::map<std::uint32_t, Delivery> deliveries;  // what each watch asked for
  std::vector<std::string> retracted;
  std::vector<std::pair<std::string, TaskOutcome>> completed;
  std::vector<std::pair<std::string, double>> reports;
  std::shared_ptr<CastError> reportError;
  std::set<std::string> lockedByOther;
  std::optional<std::chrono::milliseconds> lastLockTimeout;
  bool lastLockNoWait = false;
  LockMode lastLockMode = LockMode::O;
  bool failNextWatch = false;
  std::string sessionLanguage;
  std::string sessionKind;
  bool closed = false;
  // The identity the fake server "verified from the token"; nullopt: it does not say.
  std::optional<Identity> verified;
  // The start barrier as the runner met it (guarded by the transport's mutex:
  // read them after the runner returned, or through awaitRunCount()).
  std::vector<ComponentState> stateChanges;
  int awaitRunCalls = 0;
  std::optional<ComponentState> stateAtAwaitRun;  // the state reported when awaitRun was called
  std::shared_ptr<CastError> awaitRunError;        // awaitRun throws it (a server that refuses)

 private:
  static bool matches(const ChangeFilter& f, Operation op, const detail::EntryRecord& r, const Identity& who) {
    if (!f.operations.empty() && !f.operations.count(op)) return false;
    if (!f.type.empty() && f.type != r.type) return false;
    if (!f.id.empty() && f.id != r.address.id) return false;
    if (!f.subarchitecture.empty() && f.subarchitecture != r.address.subarchitecture) return false;
    if (!f.sourceComponent.empty() && f.sourceComponent != who.componentId) return false;
    if (!f.sourceSubarchitecture.empty() && f.sourceSubarchitecture != who.subarchitecture) return false;
    return true;
  }

  // Delivers the event outside the lock, as a stream reader thread would.
  WriteResult emit(std::unique_lock<std::mutex>& lock, Operation op, const detail::EntryRecord& r) {
    detail::EventRecord ev;
    ev.revision = r.revision;
    ev.operation = op;
    ev.address = r.address;
    ev.type = r.type;
    ev.sourceComponent = identity_.componentId;
    ev.sourceSubarchitecture = identity_.subarchitecture;
    ev.version = r.version;
    std::vector<std::uint32_t> ids;
    bool withEntry = false;
    for (const auto& [wid, filters] : watches_) {
      for (const auto& f : filters) {
        if (matches(f, op, r, identity_)) {
          ids.push_back(wid);
          withEntry = withEntry || f.includeEntry;
          break;
        }
      }
    }
    if (withEntry) ev.entry = r;
    auto sink = sink_;
    WriteResult result{r.revision, r.version};
    lock.unlock();
    if (!ids.empty() && sink) sink(ev, ids);
    return result;
  }

  Identity identity_;
  mutable std::mutex mu_;
  bool sessionStarted_ = false;
  bool barrierHeld_ = false;
  std::map<std::string, detail::EntryRecord> entries_;
  std::map<std::string, std::uint32_t> locks_;
  std::map<std::uint32_t, std::vector<ChangeFilter>> watches_;
  std::uint64_t revision_ = 0;
  int tasks_ = 0;
  detail::EventSink sink_;
  detail::ErrorSink onError_;
  detail::DecisionSink decisions_;
  detail::StateSource state_;
};

}  // namespace cast::testing
