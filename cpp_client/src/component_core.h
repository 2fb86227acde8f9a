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
#include <tuple>
#include <vector>

#include "cast/component.h"
#include "dispatcher.h"
#include "transport.h"

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

class ComponentCore : public std::enable_shared_from_this<ComponentCore> {
 public:
  explicit ComponentCore(Component* owner) : owner(owner) {}

  // The transport, or a clear error if the component was never bound.
  Transport& transport() const;
  // Cancels a watch (idempotent).
  void cancelWatch(std::uint32_t watchId);
  bool watchActive(std::uint32_t watchId);
  std::shared_ptr<CastError> watchError(std::uint32_t watchId);
  // The transport's event sink (component_watch.cc): queues the callbacks of
  // `watchIds` for `event` on the dispatcher, by each watch's options; with
  // `mayWait`, first waiting while the queue is full (which stops reading the
  // stream), else at once (a reader that looked for room first, and must not
  // stop: a shared-memory session's, which also carries the writes' replies).
  void deliver(EventRecord event, const std::vector<std::uint32_t>& watchIds, bool mayWait = true);
  // The transport's error sink: change delivery stopped for every watch.
  void deliveryFailed(const std::shared_ptr<CastError>& error);

  Component* owner;  // valid until close(); hooks run only before that
  std::shared_ptr<Transport> transport_;
  Identity identity;
  Logger log{"cast.component"};
  std::unique_ptr<Dispatcher> dispatcher;
  std::size_t maxPending = 10000;

  // One onChange registration: its callback and how its changes come.
  struct Watch {
    ChangeCallback callback;
    WatchOptions options;
  };
  // The undelivered change of one entry for a Latest watch (by watch id, SA
  // and entry id): a newer change of the entry replaces it, in its place in
  // the queue, adding up what was skipped.
  using LatestKey = std::tuple<std::uint32_t, std::string, std::string>;
  struct LatestSlot {
    std::shared_ptr<const EventRecord> event;
    std::uint64_t skipped = 0;
    std::uint64_t firstSkippedRevision = 0;
  };

  std::mutex mu;  // guards callbacks, latest, errors, nextWatchId
  std::map<std::uint32_t, Watch> callbacks;
  std::map<LatestKey, LatestSlot> latest;
  std::map<std::uint32_t, std::shared_ptr<CastError>> errors;
  std::uint32_t nextWatchId = 1;

  std::mutex schemaMu;  // held while registering, so a type is registered once
  std::set<std::pair<std::string, std::string>> registeredTypes;  // (type, SA) the SA's server was told of

  std::atomic<ComponentState> state{ComponentState::Starting};
  mutable std::mutex stopMu;
  mutable std::condition_variable stopCv;
  bool stopping = false;

  std::string idPrefix;
  std::atomic<std::uint64_t> idCounter{0};
  std::atomic<bool> closed{false};
};

}  // namespace cast::detail
