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
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include "cast/log.h"
#include "cast/types.h"
#include "event_source.h"

namespace cast::detail {

// How long one callback may run before the standby thread reads the attached sockets meanwhile.
inline constexpr std::chrono::milliseconds kStandby{10};

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
  // Reads `source` on the dispatcher thread from now on, until it ends
  // (sourceFd() -1) or is gone.
  void attach(std::weak_ptr<EventSource> source);

 private:
  // Shared with the thread, so a thread left running (stop() from a callback,
  // or a callback that hangs) never touches a destroyed Dispatcher.
  struct State {
    State(std::string name, std::size_t capacity);
    State(const State&) = delete;
    State& operator=(const State&) = delete;
    Logger log;
    std::size_t capacity;
    std::mutex mu;
    std::condition_variable wake;
    std::condition_variable idle;  // also signalled when room appears
    std::array<std::deque<std::function<void()>>, 3> queues;  // by Priority: High, Medium, Low
    std::size_t pending = 0;  // queued + running
    bool stopping = false;
    bool finished = false;
    std::vector<std::weak_ptr<EventSource>> sources;  // the attached sockets (under mu)
    bool polling = false;  // the thread waits in poll(): a submit writes wakeFd
    int wakeFd = -1;       // an eventfd the thread waits on beside its sources
    int alarmFd = -1;      // a timerfd the thread arms for kStandby at each callback's start
    int stopFd = -1;       // an eventfd that ends the standby thread
    std::atomic<bool> calling{false};  // a callback runs now
    // Set (under mu) once, when the first source starts the standby thread; read at each callback's start.
    std::atomic<bool> standbyStarted{false};
    ~State();
  };
  static void loop(const std::shared_ptr<State>& state);
  // Waits for a call or a readable source (`wait`), or reads what the sources hold now; handles it.
  static void readSources(State& s, bool wait);
  static void standBy(const std::shared_ptr<State>& state);
  static void runOne(State& s, std::function<void()>& fn);
  std::shared_ptr<State> state_;
  std::thread thread_;
  std::thread::id threadId_;
  std::thread standby_;  // started at the first attach
};

}  // namespace cast::detail
