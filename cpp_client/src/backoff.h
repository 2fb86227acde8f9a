// Reconnecting after a stream broke, shared by the three streams that open
// again by themselves (watch_stream.cc, session.cc, the decision stream in
// grpc_transport.cc): which errors are worth another try, how long to wait
// before it, and a wait that closing the connection cuts short.
#pragma once

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <mutex>
#include <random>
#include <string>

namespace cast::detail {

using Millis = std::chrono::milliseconds;

// Errors after which a stream is opened again (the server went away, or the
// connection broke); any other error ends the stream for good and is reported.
// UNAUTHENTICATED is among them because the token file may be renewed meanwhile.
inline bool transient(const std::string& code) {
  return code == "UNAVAILABLE" || code == "UNKNOWN" || code == "INTERNAL" || code == "CANCELLED" ||
         code == "DEADLINE_EXCEEDED" || code == "UNAUTHENTICATED";
}

// Exponential backoff with jitter for reconnecting: 0.1 s doubling to 3 s, so
// a restarted server is found within seconds while many clients of a server
// that is down do not all knock at the same moment.
class Backoff {
 public:
  // Back to the shortest delay (after a stream worked again).
  void reset() { next_ = kInitial; }
  // The delay to wait now; the next one is twice as long (up to 3 s).
  Millis next() {
    static thread_local std::mt19937 rng{std::random_device{}()};
    std::uniform_real_distribution<double> jitter(0.8, 1.2);
    const Millis delay(static_cast<std::int64_t>(static_cast<double>(next_.count()) * jitter(rng)));
    next_ = std::min(kMaximum, next_ * 2);
    return delay;
  }

 private:
  static constexpr Millis kInitial{100};
  static constexpr Millis kMaximum{3000};
  Millis next_{kInitial};
};

// Something to wait on that close() interrupts, so that a stream waiting to
// reconnect ends at once when the component closes.
class Closing {
 public:
  // Whether set() was called.
  bool isSet() {
    std::lock_guard<std::mutex> lock(mu_);
    return set_;
  }
  // Marks the connection closing and wakes every wait().
  void set() {
    {
      std::lock_guard<std::mutex> lock(mu_);
      set_ = true;
    }
    cv_.notify_all();
  }
  // Waits up to `delay`; true if closing.
  bool wait(Millis delay) {
    std::unique_lock<std::mutex> lock(mu_);
    return cv_.wait_for(lock, delay, [this] { return set_; });
  }

 private:
  std::mutex mu_;
  std::condition_variable cv_;
  bool set_ = false;
};

}  // namespace cast::detail
