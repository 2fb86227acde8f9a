// One thread per component that runs its callbacks one at a time: the
// highest priority first (onChange's WatchOptions::priority), in the order
// they were queued within a priority. A failing callback is logged and the
// next one runs: one bad callback must not silence the others.
//
// The queue is bounded (`capacity`), as in the Python client: a component
// whose callbacks are slow then lags behind on the server, which keeps a
// bounded history and says so (HistoryExpiredError) when the lag exceeds it,
// instead of the component growing without bound in memory. submit() from a
// stream's reader thread waits for room, which stops reading that stream.
#pragma once

#include <array>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <thread>

#include "cast/log.h"
#include "cast/types.h"

namespace cast::detail {

class Dispatcher {
 public:
  explicit Dispatcher(std::string name, std::size_t capacity = 10000);
  ~Dispatcher();
  Dispatcher(const Dispatcher&) = delete;
  Dispatcher& operator=(const Dispatcher&) = delete;

  // Queues `fn` behind the callbacks of its priority, first waiting while the
  // queue is full if `wait` (never on the dispatcher thread itself, which
  // would wait for itself); ignored once stop() was called.
  void submit(std::function<void()> fn, Priority priority = Priority::Medium, bool wait = true);
  // Waits up to `timeout` for room in the queue; whether there is. A reader
  // that queues without waiting calls it first. True once stopping (what is
  // submitted then is dropped), so that such a reader never spins on it.
  bool awaitRoom(std::chrono::milliseconds timeout);
  // Waits until everything queued so far has run; false on timeout. Called
  // on the dispatcher thread itself it cannot wait for itself: returns false.
  bool drain(std::chrono::milliseconds timeout);
  // Runs what is queued, then ends the thread (waits up to `timeout`).
  void stop(std::chrono::milliseconds timeout = std::chrono::milliseconds(5000));
  bool onThread() const { return std::this_thread::get_id() == threadId_; }

 private:
  // Shared with the thread, so a thread left running (stop() from a callback,
  // or a callback that hangs) never touches a destroyed Dispatcher.
  struct State {
    State(std::string name, std::size_t capacity) : log(std::move(name)), capacity(capacity) {}
    Logger log;
    std::size_t capacity;
    std::mutex mu;
    std::condition_variable wake;
    std::condition_variable idle;  // also signalled when room appears
    std::array<std::deque<std::function<void()>>, 3> queues;  // by Priority: High, Medium, Low
    std::size_t pending = 0;  // queued + running
    bool stopping = false;
    bool finished = false;
  };
  static void loop(const std::shared_ptr<State>& state);
  std::shared_ptr<State> state_;
  std::thread thread_;
  std::thread::id threadId_;
};

}  // namespace cast::detail
