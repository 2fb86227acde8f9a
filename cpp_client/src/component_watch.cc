// Watching, the part of the component model (cast/component.h) that turns a
// watch's changes into callbacks on the dispatcher: onChange and its options
// (Delivery, Priority), the watch handles, and the delivery of events the
// transport receives. Beside component.cc, which it shares ComponentCore with.
#include <functional>
#include <iterator>
#include <utility>

#include "cast/component.h"
#include "component_core.h"

namespace cast {

using detail::ComponentCore;

namespace detail {

void ComponentCore::cancelWatch(std::uint32_t watchId) {
  bool had;
  {
    std::lock_guard<std::mutex> lock(mu);
    had = callbacks.erase(watchId) > 0;
    // Its undelivered changes go too; their queued callbacks find nothing.
    for (auto it = latest.begin(); it != latest.end();) {
      it = std::get<0>(it->first) == watchId ? latest.erase(it) : std::next(it);
    }
  }
  if (had && transport_ && !closed) transport_->cancelWatch(watchId);
}

bool ComponentCore::watchActive(std::uint32_t watchId) {
  std::lock_guard<std::mutex> lock(mu);
  return callbacks.count(watchId) > 0;
}

std::shared_ptr<CastError> ComponentCore::watchError(std::uint32_t watchId) {
  std::lock_guard<std::mutex> lock(mu);
  auto it = errors.find(watchId);
  return it == errors.end() ? nullptr : it->second;
}

void ComponentCore::deliver(EventRecord event, const std::vector<std::uint32_t>& watchIds, bool mayWait) {
  if (!dispatcher) return;
  auto record = std::make_shared<const EventRecord>(std::move(event));
  std::shared_ptr<const WorkingMemoryChange> change;  // shared by the Queue watches
  std::weak_ptr<ComponentCore> weak = weak_from_this();
  for (std::uint32_t wid : watchIds) {
    Priority priority;
    std::function<void()> job;
    bool latestJob = false;
    {
      std::lock_guard<std::mutex> lock(mu);
      auto it = callbacks.find(wid);
      if (it == callbacks.end()) continue;
      priority = it->second.options.priority;
      if (it->second.options.delivery == Delivery::Latest) {
        LatestKey key{wid, record->address.subarchitecture, record->address.id};
        auto slot = latest.find(key);
        if (slot != latest.end()) {
          // The entry's change still waits in the queue: this one takes its
          // place, and counts it (and what it had replaced) as skipped. No
          // callback is added, so a slow consumer's queue stays as long as
          // the number of entries it watches.
          LatestSlot& s = slot->second;
          s.firstSkippedRevision = s.skipped > 0 ? s.firstSkippedRevision : s.event->revision;
          s.skipped += 1 + record->skipped;
          s.event = record;
          continue;
        }
        latest.emplace(key, LatestSlot{record, record->skipped, record->firstSkippedRevision});
        latestJob = true;
        job = [weak, key] {
          auto core = weak.lock();
          if (!core) return;
          ChangeCallback callback;
          LatestSlot taken;
          {
            std::lock_guard<std::mutex> l(core->mu);
            auto s = core->latest.find(key);
            auto w = core->callbacks.find(std::get<0>(key));
            if (s == core->latest.end() || w == core->callbacks.end()) return;  // cancelled while queued
            taken = std::move(s->second);
            core->latest.erase(s);
            callback = w->second.callback;
          }
          callback(WorkingMemoryChange(taken.event, taken.skipped, taken.firstSkippedRevision));
        };
      }
    }
    if (!job) {
      if (!change) change = std::make_shared<const WorkingMemoryChange>(record);
      job = [weak, wid, change] {
        auto core = weak.lock();
        if (!core) return;
        ChangeCallback callback;
        {
          std::lock_guard<std::mutex> l(core->mu);
          auto w = core->callbacks.find(wid);
          if (w == core->callbacks.end()) return;  // cancelled while queued: drop
          callback = w->second.callback;
        }
        callback(*change);
      };
    }
    // Not under mu: submit waits while the queue is full, which stops
    // reading the stream. A Latest watch's callback is queued at once: it
    // has one per entry at most, so these never pile up.
    dispatcher->submit(std::move(job), priority, mayWait && !latestJob);
  }
}

void ComponentCore::deliveryFailed(const std::shared_ptr<CastError>& error) {
  if (!dispatcher) return;
  {
    std::lock_guard<std::mutex> lock(mu);
    for (const auto& kv : callbacks) errors[kv.first] = error;
  }
  std::weak_ptr<ComponentCore> weak = weak_from_this();
  dispatcher->submit([weak, error] {
    auto core = weak.lock();
    if (core && !core->closed) core->owner->watchFailed(*error);
  });
}

}  // namespace detail

// ---------------------------------------------------------------- WatchHandle

void WatchHandle::cancel() {
  if (auto core = core_.lock()) core->cancelWatch(watchId_);
}

bool WatchHandle::active() const {
  auto core = core_.lock();
  return core && core->watchActive(watchId_);
}

std::shared_ptr<CastError> WatchHandle::error() const {
  auto core = core_.lock();
  return core ? core->watchError(watchId_) : nullptr;
}

// ---------------------------------------------------------------- Component

WatchHandle Component::onChange(const ChangeFilter& filter, ChangeCallback callback, const WatchOptions& options) {
  return onChange(std::vector<ChangeFilter>{filter}, std::move(callback), options);
}

WatchHandle Component::onChange(const std::vector<ChangeFilter>& filters, ChangeCallback callback,
                                const WatchOptions& options) {
  detail::Transport& t = core().transport();
  if (filters.empty()) throw InvalidArgumentError("onChange needs at least one filter");
  if (!callback) throw InvalidArgumentError("onChange needs a callback");
  std::vector<ChangeFilter> resolved;
  for (const auto& f : filters) resolved.push_back(f.resolve(subarchitecture()));
  std::uint32_t watchId;
  {
    std::lock_guard<std::mutex> lock(core().mu);
    watchId = core().nextWatchId++;
    // Registered before the watch exists, so no event can find it missing.
    core().callbacks[watchId] = ComponentCore::Watch{std::move(callback), options};
  }
  try {
    t.watch(watchId, resolved, {}, options.delivery);
  } catch (...) {
    std::lock_guard<std::mutex> lock(core().mu);
    core().callbacks.erase(watchId);
    throw;
  }
  return WatchHandle(core_, watchId);
}

bool Component::drain(std::chrono::milliseconds timeout) {
  return core().dispatcher ? core().dispatcher->drain(timeout) : true;
}

void Component::setMaxPendingCallbacks(std::size_t count) {
  if (core().dispatcher) throw CastError("setMaxPendingCallbacks must be called before bind()", "FAILED_PRECONDITION");
  core().maxPending = count == 0 ? 1 : count;
}

bool Component::onDispatcherThread() const { return core().dispatcher && core().dispatcher->onThread(); }

}  // namespace cast
