// The `transport` of the client file map (docs/design.md, "Client
// libraries"): how a component reaches its working memories. Internal, not
// installed: components never use it; Component::bind, cast::connect and the
// runner take the transport connectGrpc (cast/grpc_transport.h) returns, and
// the unit tests bind fakes of their own (tests/unit/fake_transport.h).
// Values cross this interface serialised, so nothing the component holds is
// ever shared with the WM.
#pragma once

#include <google/protobuf/descriptor.pb.h>
#include <google/protobuf/message.h>

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <future>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "cast/basic_types.h"
#include "cast/errors.h"
#include "cast/filters.h"
#include "cast/types.h"
#include "event_source.h"

namespace cast {

namespace detail {

class ClientSession;
class LoanState;

// A loan (cast/loan.h) in private memory: `header`, then `size` bytes; what a
// transport with no shared memory gives (loan.cc).
std::unique_ptr<LoanState> privateLoan(std::string header, std::size_t size);
// A loan's serialised value as bytes, for a write that sends them; its
// buffer is gone after it (loan.cc).
std::string loanBytes(LoanState& loan);

// One write of a batch.
struct BatchOp {
  Operation operation = Operation::Add;
  std::string subarchitecture;
  std::string id;
  std::string type;  // empty for delete
  std::string data;
  std::optional<std::uint64_t> expectedVersion;
};

using EventSink = std::function<void(EventRecord event, const std::vector<std::uint32_t>& watchIds)>;
using ErrorSink = std::function<void(std::shared_ptr<CastError> error)>;
using DecisionSink = std::function<void(TaskRecord task)>;
using StateSource = std::function<ComponentState()>;
// Sleeps up to the given time or until the component is asked to stop; true if it was.
using StopWait = std::function<bool(std::chrono::milliseconds)>;

class Transport {
 public:
  virtual ~Transport() = default;

  virtual const Identity& identity() const = 0;

  virtual WriteResult add(const std::string& sa, const std::string& id, const std::string& type,
                          const std::string& data) = 0;
  virtual WriteResult overwrite(const std::string& sa, const std::string& id, const std::string& type,
                                const std::string& data, std::optional<std::uint64_t> expectedVersion) = 0;
  virtual WriteResult deleteEntry(const std::string& sa, const std::string& id,
                                  std::optional<std::uint64_t> expectedVersion) = 0;
  virtual std::vector<WriteResult> batch(const std::vector<BatchOp>& ops) = 0;
  // The same writes without waiting for the answer: the future completes
  // with the result or the error add/overwrite would have thrown. Writes are
  // applied in call order. This default answers at once, by calling
  // add/overwrite (a transport without a stream has nothing to pipeline).
  virtual std::future<WriteResult> addAsync(const std::string& sa, const std::string& id, const std::string& type,
                                            const std::string& data) {
    return settled([&] { return add(sa, id, type, data); });
  }
  virtual std::future<WriteResult> overwriteAsync(const std::string& sa, const std::string& id,
                                                  const std::string& type, const std::string& data,
                                                  std::optional<std::uint64_t> expectedVersion) {
    return settled([&] { return overwrite(sa, id, type, data, expectedVersion); });
  }

  // The same four writes of a value given as its message (its type already
  // registered, its required fields set). A transport that can place a large
  // value where it is sent from (a shared-memory staging area) serialises it
  // there, with no copy between; these defaults serialise it to bytes.
  virtual WriteResult addMessage(const std::string& sa, const std::string& id, const std::string& type,
                                 const google::protobuf::Message& value) {
    return add(sa, id, type, value.SerializeAsString());
  }
  virtual WriteResult overwriteMessage(const std::string& sa, const std::string& id, const std::string& type,
                                       const google::protobuf::Message& value,
                                       std::optional<std::uint64_t> expectedVersion) {
    return overwrite(sa, id, type, value.SerializeAsString(), expectedVersion);
  }
  virtual std::future<WriteResult> addMessageAsync(const std::string& sa, const std::string& id,
                                                   const std::string& type, const google::protobuf::Message& value) {
    return addAsync(sa, id, type, value.SerializeAsString());
  }
  virtual std::future<WriteResult> overwriteMessageAsync(const std::string& sa, const std::string& id,
                                                         const std::string& type,
                                                         const google::protobuf::Message& value,
                                                         std::optional<std::uint64_t> expectedVersion) {
    return overwriteAsync(sa, id, type, value.SerializeAsString(), expectedVersion);
  }

  // A loan (cast/loan.h) of `size` bytes, after `header` (the value's other
  // fields, then the loaned field's key and length), for a write to `sa`: in
  // a region of the staging area of the session with `sa`'s server when the
  // transport has one and header + size reach its threshold, else private
  // memory (privateLoan). The caller sets its sa and type.
  virtual std::unique_ptr<LoanState> loan(const std::string& sa, std::string header, std::size_t size) = 0;
  // The same four writes of a loan's value (its type registered, the loan
  // checked: not spent, taken for `sa`). A transport whose write goes on the
  // session the loan is in names the loan's region, with no copy; these
  // defaults send its bytes. The caller spends the loan afterwards, whatever
  // happened.
  virtual WriteResult addLoan(const std::string& sa, const std::string& id, const std::string& type,
                              LoanState& loan) {
    return add(sa, id, type, loanBytes(loan));
  }
  virtual WriteResult overwriteLoan(const std::string& sa, const std::string& id, const std::string& type,
                                    LoanState& loan, std::optional<std::uint64_t> expectedVersion) {
    return overwrite(sa, id, type, loanBytes(loan), expectedVersion);
  }
  virtual std::future<WriteResult> addLoanAsync(const std::string& sa, const std::string& id,
                                                const std::string& type, LoanState& loan) {
    return addAsync(sa, id, type, loanBytes(loan));
  }
  virtual std::future<WriteResult> overwriteLoanAsync(const std::string& sa, const std::string& id,
                                                      const std::string& type, LoanState& loan,
                                                      std::optional<std::uint64_t> expectedVersion) {
    return overwriteAsync(sa, id, type, loanBytes(loan), expectedVersion);
  }

  virtual EntryRecord get(const std::string& sa, const std::string& id) = 0;
  virtual std::vector<EntryRecord> getByType(const std::string& sa, const std::string& type,
                                             std::uint32_t limit) = 0;
  virtual bool exists(const std::string& sa, const std::string& id) = 0;

  // timeout: how long to wait for another holder (nullopt: forever).
  virtual std::uint32_t lock(const std::string& sa, const std::string& id, LockMode mode,
                             std::optional<std::chrono::milliseconds> timeout, bool noWait) = 0;
  virtual std::uint32_t unlock(const std::string& sa, const std::string& id) = 0;

  // Registers .proto files (a type's file and everything it imports) with
  // the server of `sa`.
  virtual void registerSchemas(const google::protobuf::FileDescriptorSet& files, const std::string& sa) = 0;

  // Where events and stream failures go; called before the first watch.
  virtual void setEventSink(EventSink sink, ErrorSink onError) = 0;
  // How a reader that must not wait for room hands events on (a watch's
  // events on a shared-memory session's socket, docs/client-protocol.md "A
  // watch's events on the session's socket"): `now` queues without waiting,
  // `room` waits up to the time given for room in the queue (true when there
  // is). Called before the first watch, by a component with a queue; a
  // transport that never has such a reader ignores it, and one not told
  // keeps every event on its Watch call.
  // `attach` hands such a socket to the thread that runs the callbacks, which
  // reads it itself from then on (dispatcher.h).
  virtual void setSocketEvents(EventSink now, std::function<bool(std::chrono::milliseconds)> room,
                               AttachSource attach) {
    (void)now;
    (void)room;
    (void)attach;
  }
  // Creates watch `watchId` (filters already resolved) with `delivery`;
  // returns when every server involved confirmed it, with the revisions it
  // starts after.
  virtual std::map<std::string, std::uint64_t> watch(std::uint32_t watchId, const std::vector<ChangeFilter>& filters,
                                                     const std::map<std::string, std::uint64_t>& startRevisions,
                                                     Delivery delivery) = 0;
  virtual void cancelWatch(std::uint32_t watchId) = 0;

  virtual TaskRecord propose(const std::string& name, const std::string& dataType, const std::string& data,
                             std::int32_t priority) = 0;
  virtual void retract(const std::string& taskId) = 0;
  virtual void complete(const std::string& taskId, TaskOutcome outcome, const std::string& reason) = 0;
  // Opens the decision stream of the own SA's task manager.
  virtual void setDecisionSink(DecisionSink sink) = 0;

  // Records an outcome the component measured (Inspection.Report) with the
  // server of its own SA; the server refuses a bad name or value.
  virtual void report(const std::string& name, double value) = 0;

  // Registers the component's session(s) and keeps them alive.
  virtual void startSession(const std::string& language, const std::string& kind, StateSource state) = 0;
  // Who the server says the component is, having verified its token at
  // Register (RegisterResponse): Component::bind compares it with identity()
  // and takes the privilege from it, so no client decodes its token to learn
  // who it is. nullopt before startSession, and from a transport or server
  // that does not say (bind then keeps identity()).
  virtual std::optional<Identity> verifiedIdentity() const { return std::nullopt; }
  // The component's state changed: report it now rather than at the next
  // heartbeat, so tools see RUNNING / STOPPING when it happens.
  virtual void stateChanged() {}
  // Waits at the start barrier (docs/client-protocol.md, "Start-up"): the
  // runner of a component `cast run` launched calls it after start(), in
  // state STARTED. True once every component of the system has started and
  // run() may begin; false when `stopping` says the component was asked to
  // stop first (or the transport closes). Throws what the server refuses.
  virtual bool awaitRun(const StopWait& stopping) = 0;
  // Ends sessions and streams; no sink is called after close() returns.
  virtual void close() = 0;
  // The shared-memory session with the server of `sa` open now (shm.h),
  // never opening one; nullptr without one. For tests and diagnostics.
  virtual std::shared_ptr<ClientSession> sharedSession(const std::string& sa) {
    (void)sa;
    return nullptr;
  }

 private:
  // A future already holding what `write()` returned or threw.
  template <class Write>
  static std::future<WriteResult> settled(Write&& write) {
    std::promise<WriteResult> promise;
    try {
      promise.set_value(write());
    } catch (...) {
      promise.set_exception(std::current_exception());
    }
    return promise.get_future();
  }
};

}  // namespace detail
}  // namespace cast
