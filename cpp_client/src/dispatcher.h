// One thread per component that runs its callbacks one at a time, in the
// order they were queued. A failing callback is logged and the next one runs:
// one bad callback must not silence the others.
#pragma once

#include <chrono>
#include <condition_variable>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <thread>

#include "cast/log.h"

namespace cast::detail {

class Dispatcher {
 public:
  explicit Dispatcher(std::string name);
  ~Dispatcher();
  Dispatcher(const Dispatcher&) = delete;
  Dispatcher& operator=(const Dispatcher&) = delete;

  // Queues `fn`; ignored once stop() was called.
  void submit(std::function<void()> fn);
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
    explicit State(std::string name) : log(std::move(name)) {}
    Logger log;
    std::mutex mu;
    std::condition_variable wake;
    std::condition_variable idle;
    std::deque<std::function<void()>> queue;
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
