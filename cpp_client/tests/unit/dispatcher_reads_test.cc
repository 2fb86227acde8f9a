// The dispatcher thread reads the sockets attached to it and runs what they
// bring with no hand-off; a standby reads them while a callback runs long.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <future>
#include <memory>
#include <mutex>
#include <thread>
#include <vector>

#include "dispatcher.h"

namespace {

using namespace std::chrono_literals;
using cast::detail::Dispatcher;

bool eventually(const std::function<bool()>& done, std::chrono::milliseconds within = 5000ms) {
  const auto until = std::chrono::steady_clock::now() + within;
  while (!done()) {
    if (std::chrono::steady_clock::now() > until) return false;
    std::this_thread::sleep_for(1ms);
  }
  return true;
}

// A socket pair: what the test writes on one end, pump() reads from the other,
// queueing one call per byte on the dispatcher (as a session queues a frame's events).
class PairSource : public cast::detail::EventSource {
 public:
  explicit PairSource(Dispatcher& d) : d_(d) {
    int fds[2];
    EXPECT_EQ(::socketpair(AF_UNIX, SOCK_STREAM, 0, fds), 0);
    ours_ = fds[0];
    theirs_ = fds[1];
    ::fcntl(ours_, F_SETFL, O_NONBLOCK);
  }
  ~PairSource() override {
    ::close(ours_);
    ::close(theirs_);
  }
  int sourceFd() const override { return ended ? -1 : ours_; }
  bool pump() override {
    ++attempts;
    if (busy) return false;
    ++pumps;
    char buf[256];
    ssize_t n;
    while ((n = ::read(ours_, buf, sizeof buf)) > 0) {
      for (ssize_t i = 0; i < n; ++i) {
        const char c = buf[i];
        const std::thread::id reader = std::this_thread::get_id();
        d_.submit([this, c, reader] {
          std::lock_guard<std::mutex> lock(mu);
          got.push_back(c);
          readers.push_back(reader);
          runners.push_back(std::this_thread::get_id());
        }, cast::Priority::Medium, false);
      }
    }
    return true;
  }
  void send(char c) { ASSERT_EQ(::write(theirs_, &c, 1), 1); }
  std::size_t count() {
    std::lock_guard<std::mutex> lock(mu);
    return got.size();
  }

  std::mutex mu;
  std::vector<char> got;
  std::vector<std::thread::id> readers;  // the thread that read each byte
  std::vector<std::thread::id> runners;  // the thread that ran its call
  std::atomic<bool> busy{false};         // another thread reads it: pump() refuses
  std::atomic<bool> ended{false};
  std::atomic<int> pumps{0};     // reads
  std::atomic<int> attempts{0};  // reads and refusals

 private:
  Dispatcher& d_;
  int ours_ = -1;
  int theirs_ = -1;
};

TEST(DispatcherReads, WhatAnAttachedSocketBringsIsReadAndRunOnTheDispatcherThread) {
  Dispatcher d("reads");
  auto source = std::make_shared<PairSource>(d);
  d.attach(source);
  for (char c : {'a', 'b', 'c'}) {
    source->send(c);
    ASSERT_TRUE(eventually([&] { return source->count() == static_cast<std::size_t>(c - 'a' + 1); }));
  }
  std::lock_guard<std::mutex> lock(source->mu);
  EXPECT_EQ(source->got, (std::vector<char>{'a', 'b', 'c'}));
  for (std::size_t i = 0; i < 3; ++i) {
    EXPECT_EQ(source->readers[i], source->runners[i]) << "byte " << i << " was read on another thread";
    EXPECT_NE(source->readers[i], std::this_thread::get_id());
  }
}

TEST(DispatcherReads, ACallSubmittedWhileItWaitsOnTheSocketsRunsAtOnce) {
  Dispatcher d("reads");
  auto source = std::make_shared<PairSource>(d);
  d.attach(source);
  std::this_thread::sleep_for(20ms);  // the thread is asleep in poll() by now
  std::promise<std::thread::id> ran;
  d.submit([&] { ran.set_value(std::this_thread::get_id()); });
  auto future = ran.get_future();
  ASSERT_EQ(future.wait_for(5s), std::future_status::ready) << "a submit did not wake the polling thread";
  EXPECT_NE(future.get(), std::this_thread::get_id());
}

TEST(DispatcherReads, ALongCallbackLetsTheStandbyReadInItsPlace) {
  Dispatcher d("reads");
  auto source = std::make_shared<PairSource>(d);
  d.attach(source);
  std::promise<void> gate;
  std::shared_future<void> open = gate.get_future().share();
  std::atomic<bool> inside{false};
  std::thread::id dispatcher;
  d.submit([&] {
    dispatcher = std::this_thread::get_id();
    inside = true;
    open.wait();
  });
  ASSERT_TRUE(eventually([&] { return inside.load(); }));
  source->send('x');
  // Read (queued behind the long callback) while that callback still runs, by another thread.
  ASSERT_TRUE(eventually([&] { return source->pumps.load() >= 1 && d.awaitRoom(0ms); }));
  const int before = source->pumps.load();
  source->send('y');
  ASSERT_TRUE(eventually([&] { return source->pumps.load() > before; }));
  EXPECT_EQ(source->count(), 0u);  // nothing of it ran yet: the callback holds the thread
  gate.set_value();
  ASSERT_TRUE(eventually([&] { return source->count() == 2; }));
  std::lock_guard<std::mutex> lock(source->mu);
  EXPECT_NE(source->readers[0], dispatcher);
  EXPECT_EQ(source->runners[0], dispatcher);
}

TEST(DispatcherReads, ASourceAnotherThreadReadsIsLeftToItWithoutSpinning) {
  Dispatcher d("reads");
  auto source = std::make_shared<PairSource>(d);
  source->busy = true;
  d.attach(source);
  source->send('z');  // readable, and pump() refuses: the thread waits for a call or a moment (1 ms)
  std::atomic<int> calls{0};
  d.submit([&] { ++calls; });
  ASSERT_TRUE(eventually([&] { return calls.load() == 1; }));
  const int before = source->attempts.load();
  std::this_thread::sleep_for(100ms);
  // About one look per millisecond; a thread spinning on the readable socket would look millions of times.
  EXPECT_LT(source->attempts.load() - before, 1000);
  source->busy = false;
  ASSERT_TRUE(eventually([&] { return source->count() == 1; }));
}

TEST(DispatcherReads, AnEndedOrDroppedSourceIsForgottenAndStopEndsAWaitingThread) {
  auto d = std::make_unique<Dispatcher>("reads");
  auto ended = std::make_shared<PairSource>(*d);
  auto dropped = std::make_shared<PairSource>(*d);
  auto live = std::make_shared<PairSource>(*d);
  d->attach(ended);
  d->attach(dropped);
  d->attach(live);
  d->attach(live);  // attached once however often
  ended->ended = true;
  ended->send('e');  // wakes the thread: it finds the source ended and never reads it
  dropped.reset();
  live->send('l');
  ASSERT_TRUE(eventually([&] { return live->count() == 1; }));
  EXPECT_EQ(ended->pumps.load(), 0);
  EXPECT_EQ(ended->count(), 0u);
  live->send('m');
  ASSERT_TRUE(eventually([&] { return live->count() == 2; }));
  EXPECT_EQ(live->pumps.load(), 2);  // one read per byte sent apart: never twice for one attach
  const auto started = std::chrono::steady_clock::now();
  d->stop();
  EXPECT_LT(std::chrono::steady_clock::now() - started, 5s);  // the thread blocked in poll() was woken
}

TEST(DispatcherReads, AFullQueueLeavesTheSocketsUnread) {
  Dispatcher d("reads", 1);
  auto source = std::make_shared<PairSource>(d);
  d.attach(source);
  std::promise<void> gate;
  std::shared_future<void> open = gate.get_future().share();
  d.submit([&] { open.wait(); });
  d.submit([] {}, cast::Priority::Medium, false);  // the queue is full now (capacity 1, one running)
  source->send('q');
  std::this_thread::sleep_for(3 * cast::detail::kStandby);
  EXPECT_EQ(source->pumps.load(), 0);  // neither the standby nor the thread read while full
  gate.set_value();
  ASSERT_TRUE(eventually([&] { return source->count() == 1; }));
}

}  // namespace
