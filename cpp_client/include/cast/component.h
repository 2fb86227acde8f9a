// The component model (docs/design.md section 5): base classes and the working
// memory vocabulary, in C++ casing (docs/client-protocol.md, "The vocabulary").
//
// A component subclasses cast::UnmanagedComponent or cast::ManagedComponent
// and overrides lifecycle hooks. Every working-memory call is addressed to the
// component's own subarchitecture unless a subarchitecture is given (an empty
// string means the own SA). Values are protobuf messages: a write serialises
// the value at once, so later changes to the object never reach the WM, and a
// read returns a new object, so changing it never changes the WM.
//
// Every method may be called from any thread. Callbacks (onChange, task
// hooks, watchFailed) run on the component's one dispatcher thread, one at a
// time, in the order the events arrived (revision order per WM) within a
// priority (WatchOptions).
#pragma once

#include <google/protobuf/message.h>

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <future>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "cast/args.h"
#include "cast/errors.h"
#include "cast/filters.h"
#include "cast/loan.h"
#include "cast/log.h"
#include "cast/types.h"
#include "cast/views.h"

namespace cast {

class Component;

// Internal: what a component is bound to, and its state.
namespace detail {
class ComponentCore;
class LoanState;
class Transport;
}  // namespace detail

// A held lock: unlocks one level when it goes out of scope (RAII), unless
// unlock() or release() was called. Move-only.
class LockGuard {
 public:
  LockGuard() = default;
  LockGuard(LockGuard&& other) noexcept;
  LockGuard& operator=(LockGuard&& other) noexcept;
  LockGuard(const LockGuard&) = delete;
  LockGuard& operator=(const LockGuard&) = delete;
  // Unlocks if still held. A failure here (for example, the entry was deleted,
  // which releases its locks) is logged, never thrown from a destructor.
  ~LockGuard();

  // Releases this lock level now; throws the named error if the server refuses.
  void unlock();
  // Forgets the lock without unlocking it: the caller now owns that level
  // (release it with Component::unlock).
  void release() noexcept;
  // Whether this guard still holds its lock level.
  bool held() const noexcept { return held_; }
  const WorkingMemoryAddress& address() const noexcept { return address_; }
  // How many times the component held the lock when this guard took it.
  std::uint32_t depth() const noexcept { return depth_; }

 private:
  friend class Component;
  LockGuard(std::shared_ptr<detail::ComponentCore> core, WorkingMemoryAddress address, std::uint32_t depth);
  std::shared_ptr<detail::ComponentCore> core_;
  WorkingMemoryAddress address_;
  std::uint32_t depth_ = 0;
  bool held_ = false;
};

// Returned by onChange; cancel() stops the callback. Copies refer to the same
// watch.
class WatchHandle {
 public:
  WatchHandle() = default;
  // Stops delivering changes to the callback (idempotent). Changes already
  // queued for it are dropped.
  void cancel();
  // Whether the callback is still registered.
  bool active() const;
  std::uint32_t watchId() const noexcept { return watchId_; }
  // Why delivery stopped (nullptr while it runs), e.g. HistoryExpiredError.
  std::shared_ptr<CastError> error() const;

 private:
  friend class Component;
  WatchHandle(std::weak_ptr<detail::ComponentCore> core, std::uint32_t watchId)
      : core_(std::move(core)), watchId_(watchId) {}
  std::weak_ptr<detail::ComponentCore> core_;
  std::uint32_t watchId_ = 0;
};

// One write of Component::batch: build with BatchWrite::add/overwrite/erase.
struct BatchWrite {
  Operation operation = Operation::Add;
  std::string id;
  const google::protobuf::Message* value = nullptr;  // serialised when batch() is called
  std::optional<std::uint64_t> expectedVersion;

  static BatchWrite add(const std::string& id, const google::protobuf::Message& value) {
    return {Operation::Add, id, &value, std::nullopt};
  }
  static BatchWrite overwrite(const std::string& id, const google::protobuf::Message& value,
                              std::optional<std::uint64_t> expectedVersion = std::nullopt) {
    return {Operation::Overwrite, id, &value, expectedVersion};
  }
  static BatchWrite deleteEntry(const std::string& id, std::optional<std::uint64_t> expectedVersion = std::nullopt) {
    return {Operation::Delete, id, nullptr, expectedVersion};
  }
};

using ChangeCallback = std::function<void(const WorkingMemoryChange& change)>;

// What every component can do; subclass UnmanagedComponent or ManagedComponent.
class Component {
 public:
  Component();
  virtual ~Component();
  Component(const Component&) = delete;
  Component& operator=(const Component&) = delete;

  // ------------------------------------------------------------ lifecycle
  // Called first with the component's args from the configuration.
  virtual void configure(const Args& args);
  // Called after configure, before run: register callbacks here.
  virtual void start();
  // The main loop; by default waits until the component is asked to stop.
  // After run() returns the component keeps serving callbacks until stopped.
  virtual void run();
  // Called once on shutdown (SIGINT/SIGTERM, requestStop(), or run() failing).
  virtual void stop();
  // Called on the dispatcher when change delivery stopped (for example
  // HistoryExpiredError: the component fell behind the server's history).
  // The default logs it; override to resynchronise: read the current state,
  // then register the callbacks again.
  virtual void watchFailed(const CastError& error);
  // "unmanaged" or "managed", as registered with the directory.
  virtual const char* kind() const { return "unmanaged"; }

  // ------------------------------------------------------------ identity
  // Who the component is (from bind() on): its id and SA, which the server
  // verified from the token to be the ones it was started as.
  const std::string& componentId() const;
  const std::string& subarchitecture() const;
  // Whether it may write every SA, as the server verified it at Register.
  bool privileged() const;
  // A logger named after the component (cast.component.<id>).
  const Logger& log() const;

  // ------------------------------------------------------------ stopping
  // False once the component has been asked to stop.
  bool running() const;
  // Sleeps until asked to stop (true) or `timeout` passes (false); use it in
  // run() loops instead of sleep so that stopping is immediate.
  bool waitForStop(std::chrono::milliseconds timeout) const;
  void waitForStop() const;
  // Asks the runner to stop this component (stop() is then called once).
  void requestStop();

  // ------------------------------------------------------------ WM: write
  // A fresh entry id, unique across components and restarts.
  std::string newId();
  // Creates an entry; AlreadyExistsError if the id is taken.
  WriteResult add(const std::string& id, const google::protobuf::Message& value,
                  const std::string& subarchitecture = "");
  // Replaces an entry's value; ConsistencyError if expectedVersion is given
  // and differs from the entry's version.
  WriteResult overwrite(const std::string& id, const google::protobuf::Message& value,
                        const std::string& subarchitecture = "",
                        std::optional<std::uint64_t> expectedVersion = std::nullopt);
  // add and overwrite without waiting for the answer: the future of the
  // result, which the server's reply completes (future.get() throws what
  // add / overwrite would have thrown: AlreadyExistsError, ...). Many writes
  // may be in flight at once, with no need for a batch; they are applied in
  // call order. Only a value that cannot be serialised, or a component that
  // is not bound, throws here.
  std::future<WriteResult> addAsync(const std::string& id, const google::protobuf::Message& value,
                                    const std::string& subarchitecture = "");
  std::future<WriteResult> overwriteAsync(const std::string& id, const google::protobuf::Message& value,
                                          const std::string& subarchitecture = "",
                                          std::optional<std::uint64_t> expectedVersion = std::nullopt);
  // A large value written in place (cast/loan.h): the place of `value`'s
  // top-level singular bytes field `field`, `size` bytes, to fill through
  // loan.buffer() and then write with add, overwrite, addAsync or
  // overwriteAsync (the Loan&& forms below) to the same subarchitecture.
  // `value` holds every other field and leaves `field` empty; it is
  // serialised now (later changes to it are not written). Registers the
  // value's type as a write of it does. On the server's host the buffer is in
  // the staging area the server reads the value from, so nothing is copied;
  // elsewhere it is private memory (loan.shared()). InvalidArgumentError,
  // with nothing reserved, when `field` is not a top-level singular bytes
  // field of the value's type or already holds bytes.
  Loan loan(const google::protobuf::Message& value, const std::string& field, std::size_t size,
            const std::string& subarchitecture = "");
  // add, overwrite, addAsync and overwriteAsync of a loan's value (an entry
  // of the loan's value's type), as those of a message. The loan is spent by
  // the call, whatever its outcome: its buffer must not be touched after it.
  // InvalidArgumentError, the loan untouched and nothing written, when it
  // was already written or closed, or was taken for another subarchitecture
  // ("" is the component's own, for both). Batches take messages only.
  WriteResult add(const std::string& id, Loan&& loan, const std::string& subarchitecture = "");
  WriteResult overwrite(const std::string& id, Loan&& loan, const std::string& subarchitecture = "",
                        std::optional<std::uint64_t> expectedVersion = std::nullopt);
  std::future<WriteResult> addAsync(const std::string& id, Loan&& loan, const std::string& subarchitecture = "");
  std::future<WriteResult> overwriteAsync(const std::string& id, Loan&& loan, const std::string& subarchitecture = "",
                                          std::optional<std::uint64_t> expectedVersion = std::nullopt);
  // Deletes an entry (its locks go with it). `delete` is a C++ keyword, so
  // every language calls it deleteEntry / delete_entry.
  WriteResult deleteEntry(const std::string& id, const std::string& subarchitecture = "",
                          std::optional<std::uint64_t> expectedVersion = std::nullopt);
  // Applies writes in order, all or nothing, in one call. Its writes take
  // messages only (no loans).
  std::vector<WriteResult> batch(const std::vector<BatchWrite>& writes, const std::string& subarchitecture = "");

  // ------------------------------------------------------------ WM: read
  // The value of an entry as a new T; NotFoundError if missing,
  // InvalidArgumentError if the entry has another type or its stored bytes
  // do not parse as T.
  template <class T>
  T get(const std::string& id, const std::string& subarchitecture = "") {
    return detail::decodeEntry<T>(readEntry(id, subarchitecture));
  }
  // An entry with its version and author (for versioned overwrites).
  template <class T>
  Entry<T> getEntry(const std::string& id, const std::string& subarchitecture = "") {
    return detail::toEntry<T>(readEntry(id, subarchitecture));
  }
  // An entry's value, serialised, as read-only bytes that are not a copy
  // (cast/views.h): on the server's host a large value is the server's
  // shared memory, lent while the view is held; elsewhere the bytes
  // received. NotFoundError if missing.
  ValueView getView(const std::string& id, const std::string& subarchitecture = "");
  // Every entry of type T, newest first (at most `limit` if not 0).
  template <class T>
  std::vector<Entry<T>> getAll(const std::string& subarchitecture = "", std::uint32_t limit = 0) {
    std::vector<Entry<T>> out;
    for (const auto& r : readAll(typeName<T>(), subarchitecture, limit)) out.push_back(detail::toEntry<T>(r));
    return out;
  }
  // Whether an entry exists.
  bool exists(const std::string& id, const std::string& subarchitecture = "");

  // ------------------------------------------------------------ locks
  // Locks an entry, waiting for another holder up to `timeout` (nullopt:
  // forever; DeadlineExceededError when it passes). Re-entrant. The guard
  // unlocks when it goes out of scope.
  [[nodiscard]] LockGuard lock(const std::string& id, LockMode mode = LockMode::OD,
                               const std::string& subarchitecture = "",
                               std::optional<std::chrono::milliseconds> timeout = std::nullopt);
  // Locks an entry if no other component holds it; never waits. Release with
  // unlock().
  bool tryLock(const std::string& id, LockMode mode = LockMode::OD, const std::string& subarchitecture = "");
  // Releases one level of this component's lock; returns the remaining depth.
  std::uint32_t unlock(const std::string& id, const std::string& subarchitecture = "");

  // ------------------------------------------------------------ outcomes
  // Reports a measured outcome (report("answers_correct", 1)) for experiments
  // to read: the server keeps per name the count, sum, min, max and last
  // value this component reported (`cast stats`, `cast run --summary-json`,
  // `cast sweep`). InvalidArgumentError for an empty name or one over 128
  // bytes, or a value that is not finite; ResourceExhaustedError past 256
  // names. A refused report records nothing.
  void report(const std::string& name, double value);

  // ------------------------------------------------------------ watching
  // Calls `callback(change)` on the dispatcher thread for each matching
  // change, in revision order. Several filters are ORed. Returns once the
  // servers confirmed the watch, so a change made after this returns is
  // never missed. `options`: Delivery::Latest to receive only the newest
  // change of each entry the callback has not taken yet, when it falls
  // behind (change.skipped() counts the others; the server conflates too);
  // a Priority to run before (High) or after (Low) the component's other
  // pending callbacks.
  WatchHandle onChange(const ChangeFilter& filter, ChangeCallback callback, const WatchOptions& options = {});
  WatchHandle onChange(const std::vector<ChangeFilter>& filters, ChangeCallback callback,
                       const WatchOptions& options = {});
  // Waits until every callback queued so far has run; false on timeout.
  bool drain(std::chrono::milliseconds timeout = std::chrono::milliseconds(5000));
  // Whether the calling thread is this component's dispatcher thread.
  bool onDispatcherThread() const;
  // How many callbacks may wait for the dispatcher (default 10000; call
  // before bind(), e.g. in the constructor). When they are that many, the
  // component stops reading its watch streams and lags on the server, which
  // tells it (watchFailed, HistoryExpiredError) if the lag outgrows the
  // server's history: memory stays bounded, nothing is lost silently.
  void setMaxPendingCallbacks(std::size_t count);

  // ------------------------------------------------------------ binding
  // Attaches the component to a working memory system (the runner does this;
  // tests and embedding programs may too). Starts the session, and takes the
  // component's privilege from the identity the server verified; if the
  // server verified the token as another component or SA than the
  // transport's identity(), closes the connection and throws
  // InvalidArgumentError naming both.
  void bind(std::shared_ptr<detail::Transport> transport, const std::string& language = "cpp");
  // Ends the session and stops the dispatcher (after running what is queued).
  // Idempotent; the destructor calls it too, but call it before a derived
  // class's members go away if callbacks use them.
  void close();
  // The state reported in heartbeats (the runner sets it).
  void setState(ComponentState state);

 protected:
  // Called at the end of bind(); ManagedComponent opens its decision stream.
  virtual void onBound() {}
  detail::ComponentCore& core() const;
  // The serialised value, registering its type's schema with the server of
  // `sa` first if not yet done (only that server: one that hangs or is away
  // cannot hold up writes to the others).
  std::pair<std::string, std::string> serialise(const google::protobuf::Message& value, const std::string& sa);
  // The value's type name, its schema registered as serialise() does; an
  // InvalidArgumentError if the value could not be serialised (required
  // fields missing). The transport serialises it where it is sent from.
  std::string writable(const google::protobuf::Message& value, const std::string& sa);

 private:
  detail::EntryRecord readEntry(const std::string& id, const std::string& subarchitecture);
  std::vector<detail::EntryRecord> readAll(const std::string& type, const std::string& subarchitecture,
                                           std::uint32_t limit);
  std::string targetSa(const std::string& subarchitecture) const;
  // The state of a loan written to `sa`, checked (not spent, taken for `sa`).
  detail::LoanState& writableLoan(const Loan& loan, const std::string& sa) const;
  std::shared_ptr<detail::ComponentCore> core_;
};

// A component that runs continuously and pushes its results to working memory.
class UnmanagedComponent : public Component {
 public:
  const char* kind() const override { return "unmanaged"; }
};

// A component whose expensive work runs as tasks that its SA's task manager
// adopts (or rejects) according to the SA's policy.
class ManagedComponent : public Component {
 public:
  const char* kind() const override { return "managed"; }

  // Proposes a task to the own SA's task manager; the decision arrives in
  // taskAdopted / taskRejected (possibly before this returns).
  Task proposeTask(const std::string& name, std::int32_t priority = 0);
  Task proposeTask(const std::string& name, const google::protobuf::Message& data, std::int32_t priority = 0);
  // Withdraws a waiting or adopted task.
  void retractTask(const Task& task);
  void retractTask(const std::string& taskId);
  // Reports that an adopted task ended, with its outcome.
  void taskComplete(const Task& task, TaskOutcome outcome = TaskOutcome::Succeeded, const std::string& reason = "");
  void taskComplete(const std::string& taskId, TaskOutcome outcome = TaskOutcome::Succeeded,
                    const std::string& reason = "");

  // Hook: the task manager adopted `task`; do the work, then taskComplete.
  virtual void taskAdopted(const Task& task);
  // Hook: the task manager rejected `task`.
  virtual void taskRejected(const Task& task);

 protected:
  void onBound() override;
};

}  // namespace cast
