// onChange's delivery policies and priorities against the repository's Python
// server: a slow callback with Delivery::Latest sees few calls, the newest
// value right after the writer stops and an exact count of what it skipped,
// while Delivery::Queue delivers every change; with the dispatcher busy, a
// pending high-priority callback runs before pending low ones.
#include <google/protobuf/wrappers.pb.h>
#include <gtest/gtest.h>

#include <atomic>
#include <future>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "cast/cast.h"
#include "cast_server.h"

namespace {

using namespace std::chrono_literals;
using cast::Delivery;
using cast::Priority;
using cast::WatchOptions;
using cast::testing::eventually;
using cast::testing::number;
using cast::testing::sharedServer;
using google::protobuf::Int64Value;

struct Call {
  std::int64_t value;
  std::uint64_t revision;
  std::uint64_t skipped;
  std::uint64_t firstSkipped;
  bool afterWriterStopped;
};

TEST(DeliveryOnAServer, LatestSkipsWhatASlowCallbackMissedAndQueueDeliversEveryChange) {
  // motor is this test's alone: its revisions are the frame's, one apart.
  auto writer = sharedServer().connect("dl-camera", "motor");
  auto slow = sharedServer().connect("dl-slow", "motor");
  auto everyChange = sharedServer().connect("dl-every", "motor");
  const std::uint64_t start = writer->add("frame", number(0)).revision;

  std::mutex mu;
  std::vector<Call> latest;
  std::vector<Call> queued;
  std::atomic<bool> writerStopped{false};
  auto filter = cast::addressFilter("frame").withEntry();
  slow->onChange(
      filter,
      [&](const cast::WorkingMemoryChange& c) {
        {
          std::lock_guard<std::mutex> lock(mu);
          latest.push_back({c.entry<Int64Value>().value.value(), c.revision(), c.skipped(), c.firstSkippedRevision(),
                            writerStopped.load()});
        }
        std::this_thread::sleep_for(200ms);
      },
      WatchOptions{Delivery::Latest});
  everyChange->onChange(filter, [&](const cast::WorkingMemoryChange& c) {
    {
      std::lock_guard<std::mutex> lock(mu);
      queued.push_back({c.entry<Int64Value>().value.value(), c.revision(), c.skipped(), c.firstSkippedRevision(),
                        writerStopped.load()});
    }
    std::this_thread::sleep_for(10ms);
  });

  for (int i = 1; i <= 50; ++i) writer->overwrite("frame", number(i));
  writerStopped = true;
  ASSERT_TRUE(eventually([&] {
    std::lock_guard<std::mutex> lock(mu);
    return !latest.empty() && latest.back().value == 50 && queued.size() == 50;
  })) << "latest saw " << latest.size() << ", queue " << queued.size();
  ASSERT_TRUE(slow->drain(5000ms));
  std::lock_guard<std::mutex> lock(mu);

  EXPECT_LE(latest.size(), 10u) << "a 200 ms callback was called for most of 50 quick writes";
  std::uint64_t skipped = 0;
  std::uint64_t previous = start;
  std::size_t afterStop = 0;
  for (const Call& call : latest) {
    skipped += call.skipped;
    // Exactly the revisions between the previous call and this one were skipped.
    EXPECT_EQ(call.revision - previous, call.skipped + 1) << "revision " << call.revision;
    EXPECT_EQ(call.firstSkipped, call.skipped > 0 ? previous + 1 : 0) << "revision " << call.revision;
    previous = call.revision;
    afterStop += call.afterWriterStopped ? 1 : 0;
  }
  EXPECT_EQ(skipped + latest.size(), 50u);
  // The newest value comes with the first callback after the writer stopped
  // (a second only if one began while the last change was on its way).
  EXPECT_LE(afterStop, 2u);

  for (std::size_t i = 0; i < queued.size(); ++i) {
    EXPECT_EQ(queued[i].value, static_cast<std::int64_t>(i) + 1);
    EXPECT_EQ(queued[i].skipped, 0u);
  }
}

TEST(DeliveryOnAServer, APendingHighPriorityCallbackRunsBeforePendingLowOnes) {
  auto writer = sharedServer().connect("dp-writer", "language");
  auto watcher = sharedServer().connect("dp-watcher", "language");
  auto observer = sharedServer().connect("dp-observer", "language");
  std::promise<void> entered;
  std::promise<void> released;
  std::shared_future<void> release = released.get_future().share();
  std::vector<std::string> ran;  // only the watcher's dispatcher thread touches it until drained
  watcher->onChange(cast::addressFilter("dp-gate"), [&](const cast::WorkingMemoryChange&) {
    entered.set_value();
    release.wait();
  });
  auto record = [&ran](const cast::WorkingMemoryChange& c) { ran.push_back(c.id()); };
  watcher->onChange(cast::addressFilter("dp-low"), record, WatchOptions{Delivery::Queue, Priority::Low});
  watcher->onChange(cast::addressFilter("dp-medium"), record);
  watcher->onChange(cast::addressFilter("dp-high"), record, WatchOptions{Delivery::Queue, Priority::High});
  std::atomic<bool> lastWritten{false};
  observer->onChange(cast::addressFilter("dp-high"), [&](const cast::WorkingMemoryChange&) { lastWritten = true; });

  writer->add("dp-gate", number(0));
  ASSERT_EQ(entered.get_future().wait_for(20s), std::future_status::ready);
  writer->add("dp-low", number(0));
  for (int i = 1; i <= 3; ++i) writer->overwrite("dp-low", number(i));
  writer->add("dp-medium", number(0));
  writer->add("dp-high", number(0));
  // The watcher's stream carries the same events as the observer's: once the
  // observer has the last one, the watcher's are queued behind the gate too.
  ASSERT_TRUE(eventually([&] { return lastWritten.load(); }));
  std::this_thread::sleep_for(300ms);
  released.set_value();
  ASSERT_TRUE(watcher->drain(5000ms));
  EXPECT_EQ(ran, (std::vector<std::string>{"dp-high", "dp-medium", "dp-low", "dp-low", "dp-low", "dp-low"}));
}

}  // namespace
