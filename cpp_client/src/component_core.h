// The state behind a Component, shared with its LockGuards and WatchHandles
// (which may outlive it) and with the transport's sinks.
#pragma once

#include <atomic>
#include <condition_variable>
#include <map>
#include <memory>
#include <mutex>
#include <set>
#include <string>

#include "cast/component.h"
#include "dispatcher.h"

namespace cast::detail {

// The server verified the token as another component (or SA) than the one
// the component was started as. An InvalidArgumentError to whoever catches
// it; its own type only so that the runner can tell it from a failed start
// and exit 2, as for any other launch-contract error.
class IdentityMismatchError : public InvalidArgumentError {
 public:
  using InvalidArgumentError::InvalidArgumentError;
  [[noreturn]] void raise() const override { throw *this; }
};

class ComponentCore {
 public:
  explicit ComponentCore(Component* owner) : owner(owner) {}

  // The transport, or a clear error if the component was never bound.
  Transport& transport() const;
  // Cancels a watch (idempotent).
  void cancelWatch(std::uint32_t watchId);
  bool watchActive(std::uint32_t watchId);
  std::shared_ptr<CastError> watchError(std::uint32_t watchId);

  Component* owner;  // valid until close(); hooks run only before that
  std::shared_ptr<Transport> transport_;
  Identity identity;
  Logger log{"cast.component"};
  std::unique_ptr<Dispatcher> dispatcher;
  std::size_t maxPending = 10000;

  std::mutex mu;  // guards callbacks, errors, nextWatchId
  std::map<std::uint32_t, ChangeCallback> callbacks;
  std::map<std::uint32_t, std::shared_ptr<CastError>> errors;
  std::uint32_t nextWatchId = 1;

  std::mutex schemaMu;  // held while registering, so a type is registered once
  std::set<std::string> registeredTypes;

  std::atomic<ComponentState> state{ComponentState::Starting};
  mutable std::mutex stopMu;
  mutable std::condition_variable stopCv;
  bool stopping = false;

  std::string idPrefix;
  std::atomic<std::uint64_t> idCounter{0};
  std::atomic<bool> closed{false};
};

}  // namespace cast::detail
