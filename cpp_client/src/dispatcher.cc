#include "dispatcher.h"

#include <algorithm>
#include <exception>

#include "cast/errors.h"

namespace cast::detail {

Dispatcher::Dispatcher(std::string name, std::size_t capacity)
    : state_(std::make_shared<State>("cast.dispatch." + name, capacity == 0 ? 1 : capacity)) {
  thread_ = std::thread([state = state_] { loop(state); });
  threadId_ = thread_.get_id();
}

Dispatcher::~Dispatcher() { stop(); }

void Dispatcher::submit(std::function<void()> fn, Priority priority, bool wait) {
  {
    std::unique_lock<std::mutex> lock(state_->mu);
    if (wait && !onThread()) {
      state_->idle.wait(lock, [this] { return state_->pending < state_->capacity || state_->stopping; });
    }
    if (state_->stopping) return;
    state_->queues.at(static_cast<std::size_t>(priority)).push_back(std::move(fn));
    ++state_->pending;
  }
  state_->wake.notify_one();
}

void Dispatcher::loop(const std::shared_ptr<State>& s) {
  for (;;) {
    std::function<void()> fn;
    {
      std::unique_lock<std::mutex> lock(s->mu);
      auto next = s->queues.end();
      s->wake.wait(lock, [&] {
        next = std::find_if(s->queues.begin(), s->queues.end(), [](const auto& q) { return !q.empty(); });
        return next != s->queues.end() || s->stopping;
      });
      if (next == s->queues.end()) break;  // stopping and nothing left to run
      fn = std::move(next->front());
      next->pop_front();
    }
    try {
      fn();
    } catch (const CastError& e) {
      s->log.error(std::string("callback failed: ") + e.name() + ": " + e.message());
    } catch (const std::exception& e) {
      s->log.error(std::string("callback failed: ") + e.what());
    } catch (...) {
      s->log.error("callback failed with a non-standard exception");
    }
    fn = nullptr;  // destroy what the callback captured before reporting idle
    {
      std::lock_guard<std::mutex> lock(s->mu);
      --s->pending;
      s->idle.notify_all();  // room for a waiting submit, or idle for drain()
    }
  }
  std::lock_guard<std::mutex> lock(s->mu);
  s->finished = true;
  s->idle.notify_all();
}

bool Dispatcher::awaitRoom(std::chrono::milliseconds timeout) {
  std::unique_lock<std::mutex> lock(state_->mu);
  state_->idle.wait_for(lock, timeout, [this] { return state_->pending < state_->capacity || state_->stopping; });
  return state_->pending < state_->capacity || state_->stopping;
}

bool Dispatcher::drain(std::chrono::milliseconds timeout) {
  if (onThread()) return false;
  std::unique_lock<std::mutex> lock(state_->mu);
  return state_->idle.wait_for(lock, timeout, [this] { return state_->pending == 0 || state_->finished; });
}

void Dispatcher::stop(std::chrono::milliseconds timeout) {
  {
    std::lock_guard<std::mutex> lock(state_->mu);
    state_->stopping = true;
  }
  state_->wake.notify_all();
  state_->idle.notify_all();  // a submit waiting for room gives up
  if (!thread_.joinable()) return;
  if (onThread()) {
    // stop() from a callback: the thread ends after this callback returns.
    thread_.detach();
    return;
  }
  {
    std::unique_lock<std::mutex> lock(state_->mu);
    if (!state_->idle.wait_for(lock, timeout, [this] { return state_->finished; })) {
      state_->log.error("a callback was still running " + std::to_string(timeout.count()) +
                        " ms after stop; leaving the dispatcher thread behind");
      thread_.detach();
      return;
    }
  }
  thread_.join();
}

}  // namespace cast::detail
