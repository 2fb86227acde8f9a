// The dispatcher runs callbacks one at a time, in order, on one thread.
#include "dispatcher.h"

#include <gtest/gtest.h>

#include <atomic>
#include <future>
#include <set>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

namespace {

using namespace std::chrono_literals;

TEST(Dispatcher, RunsInSubmissionOrderOnOneThread) {
  cast::detail::Dispatcher d("test");
  std::vector<int> seen;
  std::set<std::thread::id> threads;
  for (int i = 0; i < 1000; ++i) {
    d.submit([&, i] {
      seen.push_back(i);
      threads.insert(std::this_thread::get_id());
    });
  }
  ASSERT_TRUE(d.drain(5000ms));
  ASSERT_EQ(seen.size(), 1000u);
  for (int i = 0; i < 1000; ++i) EXPECT_EQ(seen[static_cast<size_t>(i)], i);
  EXPECT_EQ(threads.size(), 1u);
  EXPECT_EQ(threads.count(std::this_thread::get_id()), 0u);
}

TEST(Dispatcher, AFailingCallbackDoesNotStopTheOthers) {
  cast::detail::Dispatcher d("test");
  std::atomic<int> ran{0};
  d.submit([] { throw std::runtime_error("callback bug"); });
  d.submit([&] { ++ran; });
  ASSERT_TRUE(d.drain(5000ms));
  EXPECT_EQ(ran.load(), 1);
}

TEST(Dispatcher, OneAtATime) {
  cast::detail::Dispatcher d("test");
  std::atomic<int> inside{0};
  std::atomic<int> maxInside{0};
  std::vector<std::thread> producers;
  for (int p = 0; p < 4; ++p) {
    producers.emplace_back([&] {
      for (int i = 0; i < 50; ++i) {
        d.submit([&] {
          int now = ++inside;
          int prev = maxInside.load();
          while (now > prev && !maxInside.compare_exchange_weak(prev, now)) {
          }
          std::this_thread::sleep_for(50us);
          --inside;
        });
      }
    });
  }
  for (auto& t : producers) t.join();
  ASSERT_TRUE(d.drain(10000ms));
  EXPECT_EQ(maxInside.load(), 1);
}

TEST(Dispatcher, DrainTimesOutWhileACallbackRuns) {
  cast::detail::Dispatcher d("test");
  std::atomic<bool> release{false};
  d.submit([&] {
    while (!release) std::this_thread::sleep_for(1ms);
  });
  EXPECT_FALSE(d.drain(50ms));
  release = true;
  EXPECT_TRUE(d.drain(5000ms));
}

TEST(Dispatcher, StopRunsWhatIsQueuedThenIgnoresNewWork) {
  cast::detail::Dispatcher d("test");
  std::atomic<int> ran{0};
  for (int i = 0; i < 10; ++i) d.submit([&] { ++ran; });
  d.stop();
  EXPECT_EQ(ran.load(), 10);
  d.submit([&] { ++ran; });
  std::this_thread::sleep_for(20ms);
  EXPECT_EQ(ran.load(), 10);
}

TEST(Dispatcher, DrainOnTheDispatcherThreadDoesNotDeadlock) {
  cast::detail::Dispatcher d("test");
  std::atomic<int> result{-1};
  d.submit([&] { result = d.drain(1000ms) ? 1 : 0; });
  ASSERT_TRUE(d.drain(5000ms));
  EXPECT_EQ(result.load(), 0);
}

}  // namespace

namespace {

TEST(Dispatcher, AFullQueueHoldsTheSubmitterBack) {
  cast::detail::Dispatcher d("test", 2);
  std::atomic<bool> release{false};
  std::atomic<int> ran{0};
  d.submit([&] {
    while (!release) std::this_thread::sleep_for(1ms);
    ++ran;
  });
  d.submit([&] { ++ran; });  // the queue holds two: full now
  std::atomic<bool> submitted{false};
  std::thread producer([&] {
    d.submit([&] { ++ran; });
    submitted = true;
  });
  std::this_thread::sleep_for(50ms);
  EXPECT_FALSE(submitted) << "submit must wait for room";
  release = true;
  producer.join();
  EXPECT_TRUE(submitted);
  ASSERT_TRUE(d.drain(5000ms));
  EXPECT_EQ(ran.load(), 3);
}

TEST(Dispatcher, TheDispatcherThreadNeverWaitsForItself) {
  cast::detail::Dispatcher d("test", 1);
  std::atomic<int> ran{0};
  d.submit([&] {
    d.submit([&] { ++ran; });  // full, but waiting here would deadlock
    ++ran;
  });
  ASSERT_TRUE(d.drain(5000ms));
  EXPECT_EQ(ran.load(), 2);
}

TEST(Dispatcher, StopReleasesAWaitingSubmitter) {
  auto d = std::make_unique<cast::detail::Dispatcher>("test", 1);
  std::atomic<bool> release{false};
  d->submit([&] {
    while (!release) std::this_thread::sleep_for(1ms);
  });
  std::thread producer([&] { d->submit([] {}); });
  std::this_thread::sleep_for(30ms);
  std::thread stopper([&] { d->stop(5000ms); });
  std::this_thread::sleep_for(30ms);
  release = true;
  producer.join();  // returns: stop() woke it, its call is dropped
  stopper.join();
  SUCCEED();
}

// Callbacks pending behind a busy one run highest priority first, in the
// order they were queued within a priority.
TEST(Dispatcher, AwaitRoomSaysWhetherTheQueueHasRoomAndNeverHoldsBackOnceStopping) {
  // What a reader that queues without waiting (a shared-memory session's) looks at first.
  cast::detail::Dispatcher d("test", 1);
  EXPECT_TRUE(d.awaitRoom(0ms));
  std::promise<void> release;
  std::shared_future<void> released = release.get_future().share();
  d.submit([released] { released.wait(); });
  EXPECT_FALSE(d.awaitRoom(20ms));  // full: the one callback runs
  std::thread later([&] {
    std::this_thread::sleep_for(20ms);
    release.set_value();
  });
  EXPECT_TRUE(d.awaitRoom(5000ms));  // room as soon as it returned
  later.join();
  d.submit([released] { released.wait(); });
  d.stop();
  EXPECT_TRUE(d.awaitRoom(0ms));  // stopping: nothing is queued, nothing waits
}

TEST(Dispatcher, TheHighestPriorityPendingCallbackRunsFirst) {
  using cast::Priority;
  cast::detail::Dispatcher d("test");
  std::atomic<bool> release{false};
  std::vector<std::string> ran;  // only the dispatcher thread appends
  d.submit([&] {
    while (!release) std::this_thread::sleep_for(1ms);
  });
  d.submit([&] { ran.push_back("low 1"); }, Priority::Low);
  d.submit([&] { ran.push_back("medium 1"); });
  d.submit([&] { ran.push_back("low 2"); }, Priority::Low);
  d.submit([&] { ran.push_back("high 1"); }, Priority::High);
  d.submit([&] { ran.push_back("medium 2"); }, Priority::Medium);
  d.submit([&] { ran.push_back("high 2"); }, Priority::High);
  release = true;
  ASSERT_TRUE(d.drain(5000ms));
  EXPECT_EQ(ran, (std::vector<std::string>{"high 1", "high 2", "medium 1", "medium 2", "low 1", "low 2"}));
}

// A callback queued without waiting (a Latest watch's) goes in even when the
// queue is full.
TEST(Dispatcher, ASubmitThatMayNotWaitIsQueuedAtOnce) {
  cast::detail::Dispatcher d("test", 1);
  std::atomic<bool> release{false};
  std::atomic<int> ran{0};
  d.submit([&] {
    while (!release) std::this_thread::sleep_for(1ms);
  });
  auto submitted = std::async(std::launch::async, [&] { d.submit([&] { ++ran; }, cast::Priority::Medium, false); });
  EXPECT_EQ(submitted.wait_for(5s), std::future_status::ready) << "the queue is full, and it must not wait";
  release = true;
  submitted.wait();
  ASSERT_TRUE(d.drain(5000ms));
  EXPECT_EQ(ran.load(), 1);
}

}  // namespace
