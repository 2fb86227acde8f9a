#include "cast/component.h"

#include <random>
#include <sstream>

#include "cast/schemas.h"
#include "component_core.h"
#include "loan_state.h"

namespace cast {

using detail::ComponentCore;

// ---------------------------------------------------------------- core

namespace detail {

Transport& ComponentCore::transport() const {
  if (!transport_) {
    throw CastError(
        "the component is not bound to a working memory system: run it with CAST_COMPONENT_MAIN, or call bind()",
        "FAILED_PRECONDITION");
  }
  if (closed) throw CastError("the component was closed: its session has ended", "FAILED_PRECONDITION");
  return *transport_;
}

}  // namespace detail

// ---------------------------------------------------------------- LockGuard

LockGuard::LockGuard(std::shared_ptr<ComponentCore> core, WorkingMemoryAddress address, std::uint32_t depth)
    : core_(std::move(core)), address_(std::move(address)), depth_(depth), held_(true) {}

LockGuard::LockGuard(LockGuard&& other) noexcept
    : core_(std::move(other.core_)), address_(std::move(other.address_)), depth_(other.depth_), held_(other.held_) {
  other.held_ = false;
}

LockGuard& LockGuard::operator=(LockGuard&& other) noexcept {
  if (this != &other) {
    if (held_) {
      try {
        unlock();
      } catch (...) {  // logged by the destructor path below; nothing to do here
      }
    }
    core_ = std::move(other.core_);
    address_ = std::move(other.address_);
    depth_ = other.depth_;
    held_ = other.held_;
    other.held_ = false;
  }
  return *this;
}

LockGuard::~LockGuard() {
  if (!held_) return;
  try {
    unlock();
  } catch (const CastError& e) {
    core_->log.warning("unlock of " + address_.subarchitecture + "/" + address_.id +
                       " at the end of its guard failed: " + e.name() + ": " + e.message());
  } catch (const std::exception& e) {
    core_->log.warning("unlock of " + address_.subarchitecture + "/" + address_.id + " failed: " + e.what());
  }
}

void LockGuard::unlock() {
  if (!held_) return;
  held_ = false;  // one attempt only: a failed unlock is not retried by the destructor
  core_->transport().unlock(address_.subarchitecture, address_.id);
}

void LockGuard::release() noexcept { held_ = false; }

// ---------------------------------------------------------------- Component

namespace {

// Takes the privilege from the identity the server verified at Register (its
// word, not the token's claims: it is what the server enforces). Returns the
// error message when the server verified the token as another component or
// SA than the one the component was started as; nullopt otherwise, also when
// the transport does not say (the component then keeps what it was given).
std::optional<std::string> adoptVerifiedIdentity(ComponentCore& c) {
  const std::optional<Identity> verified = c.transport_->verifiedIdentity();
  if (!verified) return std::nullopt;
  const Identity& started = c.identity;
  if (verified->componentId != started.componentId || verified->subarchitecture != started.subarchitecture) {
    return "this component was started as '" + started.componentId + "' in subarchitecture '" +
           started.subarchitecture + "' (CAST_COMPONENT_ID, CAST_SUBARCHITECTURE), but the server verified its " +
           "token as '" + verified->componentId + "' in subarchitecture '" + verified->subarchitecture +
           "': the token was issued for another component; give it a token for '" + started.componentId +
           "' (`cast token " + started.componentId + " --sa " + started.subarchitecture +
           "`), or start it with `cast run CONFIG`";
  }
  c.identity.privileged = verified->privileged;
  return std::nullopt;
}

}  // namespace

Component::Component() : core_(std::make_shared<ComponentCore>(this)) {}

Component::~Component() {
  try {
    close();
  } catch (...) {  // a destructor must not throw; close() logs what failed
  }
}

ComponentCore& Component::core() const { return *core_; }

void Component::configure(const Args&) {}
void Component::start() {}
void Component::run() { waitForStop(); }
void Component::stop() {}

void Component::watchFailed(const CastError& error) {
  log().error(std::string("change delivery stopped: ") + error.name() + ": " + error.message());
}

const std::string& Component::componentId() const { return core_->identity.componentId; }
const std::string& Component::subarchitecture() const { return core_->identity.subarchitecture; }
bool Component::privileged() const { return core_->identity.privileged; }
const Logger& Component::log() const { return core_->log; }

bool Component::running() const {
  std::lock_guard<std::mutex> lock(core_->stopMu);
  return !core_->stopping;
}

bool Component::waitForStop(std::chrono::milliseconds timeout) const {
  std::unique_lock<std::mutex> lock(core_->stopMu);
  return core_->stopCv.wait_for(lock, timeout, [this] { return core_->stopping; });
}

void Component::waitForStop() const {
  std::unique_lock<std::mutex> lock(core_->stopMu);
  core_->stopCv.wait(lock, [this] { return core_->stopping; });
}

void Component::requestStop() {
  {
    std::lock_guard<std::mutex> lock(core_->stopMu);
    core_->stopping = true;
  }
  core_->stopCv.notify_all();
}

void Component::setState(ComponentState state) {
  if (core_->state.exchange(state) != state && core_->transport_ && !core_->closed) core_->transport_->stateChanged();
}

void Component::bind(std::shared_ptr<detail::Transport> transport, const std::string& language) {
  if (core_->transport_) throw CastError("the component is already bound", "FAILED_PRECONDITION");
  if (!transport) throw InvalidArgumentError("bind() needs a transport");
  ComponentCore& c = *core_;
  c.identity = transport->identity();
  c.log = Logger("cast.component." + c.identity.componentId);
  c.dispatcher = std::make_unique<detail::Dispatcher>(c.identity.componentId, c.maxPending);
  // A random part per process keeps ids unique across restarts of the same
  // component (the counter starts again at 1).
  std::random_device rd;
  std::ostringstream prefix;
  prefix << c.identity.componentId << ":" << std::hex;
  for (int i = 0; i < 3; ++i) {
    unsigned byte = rd() & 0xffu;
    if (byte < 16) prefix << '0';
    prefix << byte;
  }
  prefix << ":";
  c.idPrefix = prefix.str();
  c.transport_ = std::move(transport);

  std::weak_ptr<ComponentCore> weak = core_;
  c.transport_->setEventSink(
      [weak](detail::EventRecord event, const std::vector<std::uint32_t>& watchIds) {
        if (auto core = weak.lock()) core->deliver(std::move(event), watchIds);
      },
      [weak](std::shared_ptr<CastError> error) {
        if (auto core = weak.lock()) core->deliveryFailed(error);
      });
  c.transport_->setSocketEvents(
      [weak](detail::EventRecord event, const std::vector<std::uint32_t>& watchIds) {
        if (auto core = weak.lock()) core->deliver(std::move(event), watchIds, false);
      },
      [weak](std::chrono::milliseconds timeout) {
        auto core = weak.lock();
        // A component gone has nothing to hold back: its events are dropped.
        return !core || !core->dispatcher || core->dispatcher->awaitRoom(timeout);
      },
      [weak](std::weak_ptr<detail::EventSource> source) {
        if (auto core = weak.lock()) {
          if (core->dispatcher) core->dispatcher->attach(std::move(source));
        }
      });
  std::weak_ptr<ComponentCore> weakState = core_;
  c.transport_->startSession(language, kind(), [weakState] {
    auto core = weakState.lock();
    return core ? core->state.load() : ComponentState::Stopping;
  });
  if (auto mismatch = adoptVerifiedIdentity(c)) {
    // Nothing may act under an identity that is not the component's: the
    // connection closes now, before any hook runs.
    close();
    throw detail::IdentityMismatchError(*mismatch);
  }
  onBound();
}

void Component::close() {
  ComponentCore& c = *core_;
  if (c.closed.exchange(true)) return;
  requestStop();
  if (c.dispatcher) c.dispatcher->stop();
  if (c.transport_) {
    try {
      c.transport_->close();
    } catch (const std::exception& e) {
      c.log.warning(std::string("closing the connection failed: ") + e.what());
    }
  }
}

std::string Component::targetSa(const std::string& subarchitecture) const {
  return subarchitecture.empty() ? core_->identity.subarchitecture : subarchitecture;
}

std::string Component::newId() {
  if (core_->idPrefix.empty()) core().transport();  // throws the "not bound" error
  return core_->idPrefix + std::to_string(++core_->idCounter);
}

std::string Component::writable(const google::protobuf::Message& value, const std::string& sa) {
  detail::Transport& t = core().transport();
  const google::protobuf::Descriptor* descriptor = value.GetDescriptor();
  const std::string& name = descriptor->full_name();
  {
    std::lock_guard<std::mutex> lock(core_->schemaMu);
    if (core_->registeredTypes.count({name, sa}) == 0) {
      t.registerSchemas(schemaFilesOf(descriptor), sa);
      core_->registeredTypes.insert({name, sa});
    }
  }
  if (!value.IsInitialized()) {
    throw InvalidArgumentError("value of type " + name + " could not be serialised (required fields missing?)");
  }
  return name;
}

std::pair<std::string, std::string> Component::serialise(const google::protobuf::Message& value,
                                                         const std::string& sa) {
  std::string name = writable(value, sa);
  std::string data;
  if (!value.SerializeToString(&data)) {
    throw InvalidArgumentError("value of type " + name + " could not be serialised (required fields missing?)");
  }
  return {std::move(name), std::move(data)};
}

WriteResult Component::add(const std::string& id, const google::protobuf::Message& value,
                           const std::string& subarchitecture) {
  const std::string sa = targetSa(subarchitecture);
  const std::string type = writable(value, sa);
  return core().transport().addMessage(sa, id, type, value);
}

WriteResult Component::overwrite(const std::string& id, const google::protobuf::Message& value,
                                 const std::string& subarchitecture, std::optional<std::uint64_t> expectedVersion) {
  const std::string sa = targetSa(subarchitecture);
  const std::string type = writable(value, sa);
  return core().transport().overwriteMessage(sa, id, type, value, expectedVersion);
}

std::future<WriteResult> Component::addAsync(const std::string& id, const google::protobuf::Message& value,
                                             const std::string& subarchitecture) {
  const std::string sa = targetSa(subarchitecture);
  const std::string type = writable(value, sa);
  return core().transport().addMessageAsync(sa, id, type, value);
}

std::future<WriteResult> Component::overwriteAsync(const std::string& id, const google::protobuf::Message& value,
                                                   const std::string& subarchitecture,
                                                   std::optional<std::uint64_t> expectedVersion) {
  const std::string sa = targetSa(subarchitecture);
  const std::string type = writable(value, sa);
  return core().transport().overwriteMessageAsync(sa, id, type, value, expectedVersion);
}

// ---------------------------------------------------------------- loans

Loan Component::loan(const google::protobuf::Message& value, const std::string& field, std::size_t size,
                     const std::string& subarchitecture) {
  const std::string sa = targetSa(subarchitecture);
  std::string header = detail::loanHeader(value, field, size);  // the field checked before anything is asked
  const std::string type = writable(value, sa);
  std::unique_ptr<detail::LoanState> state = core().transport().loan(sa, std::move(header), size);
  state->sa = sa;
  state->type = type;
  return detail::LoanAccess::make(std::move(state));
}

detail::LoanState& Component::writableLoan(const Loan& loan, const std::string& sa) const {
  detail::LoanState* state = detail::LoanAccess::state(loan);
  if (state == nullptr || state->spent()) {
    throw InvalidArgumentError("this loan was already written (or closed): take a new loan for each write");
  }
  if (state->sa != sa) {
    throw InvalidArgumentError("the loan was taken for subarchitecture '" + state->sa + "' and is written to '" + sa +
                               "': take it with subarchitecture '" + sa + "'");
  }
  return *state;
}

namespace {

// Spends a loan when the write that took it returns or throws: its region, if
// the write did not take it, goes back.
class SpendOnExit {
 public:
  explicit SpendOnExit(detail::LoanState& loan) : loan_(loan) {}
  SpendOnExit(const SpendOnExit&) = delete;
  SpendOnExit& operator=(const SpendOnExit&) = delete;
  ~SpendOnExit() { loan_.spend(); }

 private:
  detail::LoanState& loan_;
};

}  // namespace

WriteResult Component::add(const std::string& id, Loan&& loan, const std::string& subarchitecture) {
  const std::string sa = targetSa(subarchitecture);
  detail::LoanState& state = writableLoan(loan, sa);
  SpendOnExit spend(state);
  return core().transport().addLoan(sa, id, state.type, state);
}

WriteResult Component::overwrite(const std::string& id, Loan&& loan, const std::string& subarchitecture,
                                 std::optional<std::uint64_t> expectedVersion) {
  const std::string sa = targetSa(subarchitecture);
  detail::LoanState& state = writableLoan(loan, sa);
  SpendOnExit spend(state);
  return core().transport().overwriteLoan(sa, id, state.type, state, expectedVersion);
}

std::future<WriteResult> Component::addAsync(const std::string& id, Loan&& loan, const std::string& subarchitecture) {
  const std::string sa = targetSa(subarchitecture);
  detail::LoanState& state = writableLoan(loan, sa);
  SpendOnExit spend(state);
  return core().transport().addLoanAsync(sa, id, state.type, state);
}

std::future<WriteResult> Component::overwriteAsync(const std::string& id, Loan&& loan,
                                                   const std::string& subarchitecture,
                                                   std::optional<std::uint64_t> expectedVersion) {
  const std::string sa = targetSa(subarchitecture);
  detail::LoanState& state = writableLoan(loan, sa);
  SpendOnExit spend(state);
  return core().transport().overwriteLoanAsync(sa, id, state.type, state, expectedVersion);
}

WriteResult Component::deleteEntry(const std::string& id, const std::string& subarchitecture,
                                   std::optional<std::uint64_t> expectedVersion) {
  return core().transport().deleteEntry(targetSa(subarchitecture), id, expectedVersion);
}

std::vector<WriteResult> Component::batch(const std::vector<BatchWrite>& writes, const std::string& subarchitecture) {
  std::vector<detail::BatchOp> ops;
  const std::string target = targetSa(subarchitecture);
  for (const auto& w : writes) {
    detail::BatchOp op;
    op.operation = w.operation;
    op.subarchitecture = target;
    op.id = w.id;
    op.expectedVersion = w.expectedVersion;
    if (w.operation != Operation::Delete) {
      if (w.value == nullptr) {
        throw InvalidArgumentError(std::string("batch ") + toString(w.operation) + " of '" + w.id + "' needs a value");
      }
      std::tie(op.type, op.data) = serialise(*w.value, target);
    }
    ops.push_back(std::move(op));
  }
  if (ops.empty()) return {};
  return core().transport().batch(ops);
}

detail::EntryRecord Component::readEntry(const std::string& id, const std::string& subarchitecture) {
  return core().transport().get(targetSa(subarchitecture), id);
}

std::vector<detail::EntryRecord> Component::readAll(const std::string& type, const std::string& subarchitecture,
                                                    std::uint32_t limit) {
  return core().transport().getByType(targetSa(subarchitecture), type, limit);
}

ValueView Component::getView(const std::string& id, const std::string& subarchitecture) {
  return ValueView(std::make_shared<const detail::EntryRecord>(readEntry(id, subarchitecture)));
}

bool Component::exists(const std::string& id, const std::string& subarchitecture) {
  return core().transport().exists(targetSa(subarchitecture), id);
}

LockGuard Component::lock(const std::string& id, LockMode mode, const std::string& subarchitecture,
                          std::optional<std::chrono::milliseconds> timeout) {
  const std::string target = targetSa(subarchitecture);
  std::uint32_t depth = core().transport().lock(target, id, mode, timeout, false);
  return LockGuard(core_, WorkingMemoryAddress{id, target}, depth);
}

bool Component::tryLock(const std::string& id, LockMode mode, const std::string& subarchitecture) {
  try {
    core().transport().lock(targetSa(subarchitecture), id, mode, std::nullopt, true);
  } catch (const LockedError&) {
    return false;
  }
  return true;
}

std::uint32_t Component::unlock(const std::string& id, const std::string& subarchitecture) {
  return core().transport().unlock(targetSa(subarchitecture), id);
}

void Component::report(const std::string& name, double value) { core().transport().report(name, value); }

// ---------------------------------------------------------------- ManagedComponent

void ManagedComponent::onBound() {
  // The sink may capture `this`: the transport calls no sink after close(),
  // and close() runs before the component goes away.
  ComponentCore& c = core();
  c.transport().setDecisionSink([this, &c](detail::TaskRecord record) {
    if (c.closed || !c.dispatcher) return;
    auto task = std::make_shared<const Task>(std::move(record));
    if (task->state() == TaskState::Adopted) {
      c.dispatcher->submit([this, task] { taskAdopted(*task); });
    } else if (task->state() == TaskState::Rejected) {
      c.dispatcher->submit([this, task] { taskRejected(*task); });
    }
  });
}

Task ManagedComponent::proposeTask(const std::string& name, std::int32_t priority) {
  return Task(core().transport().propose(name, "", "", priority));
}

Task ManagedComponent::proposeTask(const std::string& name, const google::protobuf::Message& data,
                                   std::int32_t priority) {
  auto [type, bytes] = serialise(data, core().identity.subarchitecture);
  return Task(core().transport().propose(name, type, bytes, priority));
}

void ManagedComponent::retractTask(const Task& task) { retractTask(task.taskId()); }
void ManagedComponent::retractTask(const std::string& taskId) { core().transport().retract(taskId); }

void ManagedComponent::taskComplete(const Task& task, TaskOutcome outcome, const std::string& reason) {
  taskComplete(task.taskId(), outcome, reason);
}

void ManagedComponent::taskComplete(const std::string& taskId, TaskOutcome outcome, const std::string& reason) {
  core().transport().complete(taskId, outcome, reason);
}

void ManagedComponent::taskAdopted(const Task& task) {
  log().info("task " + task.taskId() + " '" + task.name() + "' adopted; override taskAdopted to run it");
}

void ManagedComponent::taskRejected(const Task& task) {
  log().info("task " + task.taskId() + " '" + task.name() + "' rejected: " + task.reason());
}

}  // namespace cast
