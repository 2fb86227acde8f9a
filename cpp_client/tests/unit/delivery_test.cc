// onChange's options in the component (component_watch.cc), with a transport
// that delivers each change as it is written: a Latest watch keeps one
// undelivered change per entry and counts what it replaced, a Queue watch
// gets every change, priorities order what is pending, and the delivery asked
// for reaches the transport. Against a real server: tests/server/delivery_test.cc.
#include <google/protobuf/wrappers.pb.h>
#include <gtest/gtest.h>

#include <chrono>
#include <future>
#include <string>
#include <vector>

#include "cast/component.h"
#include "fake_transport.h"

namespace {

using namespace std::chrono_literals;
using cast::Delivery;
using cast::Priority;
using cast::WatchOptions;
using cast::testing::FakeTransport;
using google::protobuf::Int64Value;

Int64Value number(std::int64_t n) {
  Int64Value v;
  v.set_value(n);
  return v;
}

struct Seen {
  std::string id;
  std::int64_t value;
  std::uint64_t revision;
  std::uint64_t skipped;
  std::uint64_t firstSkipped;
};

// A component whose dispatcher is held by a callback until release() (so
// changes wait in its queue), on a fake transport.
class Held : public ::testing::Test {
 protected:
  void SetUp() override {
    transport = std::make_shared<FakeTransport>(cast::Identity{"watcher", "vision", false});
    component.bind(transport);
    component.onChange(cast::addressFilter("gate"), [this](const cast::WorkingMemoryChange&) {
      entered.set_value();
      released.get_future().wait();
    });
    component.add("gate", number(0));
    ASSERT_EQ(entered.get_future().wait_for(5s), std::future_status::ready);
  }
  void release() {
    released.set_value();
    ASSERT_TRUE(component.drain(5000ms));
  }
  void TearDown() override { component.close(); }

  std::shared_ptr<FakeTransport> transport;
  cast::UnmanagedComponent component;
  std::promise<void> entered;
  std::promise<void> released;
};

std::function<void(const cast::WorkingMemoryChange&)> recorder(std::vector<Seen>& seen) {
  return [&seen](const cast::WorkingMemoryChange& c) {
    seen.push_back({c.id(), c.entry<Int64Value>().value.value(), c.revision(), c.skipped(), c.firstSkippedRevision()});
  };
}

TEST_F(Held, ALatestWatchGetsTheNewestChangeOfEachEntryAndCountsWhatItSkipped) {
  std::vector<Seen> latest;
  std::vector<Seen> queue;
  const auto filter = cast::localTypeFilter<Int64Value>().withEntry();
  component.onChange(filter, recorder(latest), WatchOptions{Delivery::Latest});
  component.onChange(filter, recorder(queue));
  const std::uint64_t aFirst = component.add("a", number(0)).revision;
  for (int i = 1; i <= 4; ++i) component.overwrite("a", number(i));
  const std::uint64_t bFirst = component.add("b", number(10)).revision;
  component.overwrite("b", number(11));
  const std::uint64_t bLast = component.overwrite("b", number(12)).revision;
  const std::uint64_t aLast = component.overwrite("a", number(5)).revision;
  release();

  // The newest of each entry, in the place its first undelivered change had.
  ASSERT_EQ(latest.size(), 2u);
  EXPECT_EQ(latest[0].id, "a");
  EXPECT_EQ(latest[0].value, 5);
  EXPECT_EQ(latest[0].revision, aLast);
  EXPECT_EQ(latest[0].skipped, 5u);
  EXPECT_EQ(latest[0].firstSkipped, aFirst);
  EXPECT_EQ(latest[1].id, "b");
  EXPECT_EQ(latest[1].value, 12);
  EXPECT_EQ(latest[1].revision, bLast);
  EXPECT_EQ(latest[1].skipped, 2u);
  EXPECT_EQ(latest[1].firstSkipped, bFirst);
  // The queue watch of the same changes misses none.
  ASSERT_EQ(queue.size(), 9u);
  for (std::size_t i = 1; i < queue.size(); ++i) EXPECT_LT(queue[i - 1].revision, queue[i].revision);
  for (const Seen& s : queue) EXPECT_EQ(s.skipped, 0u);
}

TEST_F(Held, ChangesTakenOneAtATimeAreNotSkipped) {
  std::vector<Seen> latest;
  component.onChange(cast::addressFilter("a").withEntry(), recorder(latest), WatchOptions{Delivery::Latest});
  component.add("a", number(0));
  release();
  component.overwrite("a", number(1));
  ASSERT_TRUE(component.drain(5000ms));
  ASSERT_EQ(latest.size(), 2u);
  EXPECT_EQ(latest[1].value, 1);
  EXPECT_EQ(latest[1].skipped, 0u);
  EXPECT_EQ(latest[1].firstSkipped, 0u);
}

// What the server skipped before a change adds to what the queue skipped.
TEST_F(Held, SkippedCountsAddUpWithTheServers) {
  std::vector<Seen> latest;
  auto handle = component.onChange(cast::addressFilter("a").withEntry(), recorder(latest),
                                   WatchOptions{Delivery::Latest});
  cast::detail::EventRecord first;
  first.revision = 10;
  first.address = {"a", "vision"};
  first.type = "google.protobuf.Int64Value";
  first.entry = cast::detail::EntryRecord{{"a", "vision"}, first.type, number(7).SerializeAsString(), 0, "w", 10, 0};
  first.skipped = 2;
  first.firstSkippedRevision = 8;
  cast::detail::EventRecord second = first;
  second.revision = 14;
  second.skipped = 3;
  second.firstSkippedRevision = 11;
  transport->deliver(first, {handle.watchId()});
  transport->deliver(second, {handle.watchId()});
  release();
  ASSERT_EQ(latest.size(), 1u);
  EXPECT_EQ(latest[0].revision, 14u);
  EXPECT_EQ(latest[0].skipped, 2u + 1u + 3u);  // 8, 9; 10; 11, 12, 13
  EXPECT_EQ(latest[0].firstSkipped, 8u);
}

TEST_F(Held, ACancelledLatestWatchDropsItsWaitingChange) {
  std::vector<Seen> latest;
  auto handle = component.onChange(cast::addressFilter("a").withEntry(), recorder(latest),
                                   WatchOptions{Delivery::Latest});
  component.add("a", number(0));
  handle.cancel();
  release();
  EXPECT_TRUE(latest.empty());
}

TEST_F(Held, PendingCallbacksRunByPriority) {
  std::vector<std::string> ran;
  auto record = [&ran](const cast::WorkingMemoryChange& c) { ran.push_back(c.id()); };
  component.onChange(cast::addressFilter("low"), record, WatchOptions{Delivery::Queue, Priority::Low});
  component.onChange(cast::addressFilter("medium"), record);
  component.onChange(cast::addressFilter("high"), record, WatchOptions{Delivery::Latest, Priority::High});
  component.add("low", number(1));
  component.add("medium", number(1));
  component.overwrite("low", number(2));
  component.add("high", number(1));
  release();
  EXPECT_EQ(ran, (std::vector<std::string>{"high", "medium", "low", "low"}));
}

TEST(Delivery, TheDeliveryAskedForReachesTheTransport) {
  auto transport = std::make_shared<FakeTransport>(cast::Identity{"watcher", "vision", false});
  cast::UnmanagedComponent component;
  component.bind(transport);
  auto queued = component.onChange(cast::addressFilter("a"), [](const cast::WorkingMemoryChange&) {});
  auto latest = component.onChange(cast::addressFilter("a"), [](const cast::WorkingMemoryChange&) {},
                                   WatchOptions{Delivery::Latest, Priority::Low});
  EXPECT_EQ(transport->deliveries.at(queued.watchId()), Delivery::Queue);
  EXPECT_EQ(transport->deliveries.at(latest.watchId()), Delivery::Latest);
  component.close();
}

// A transport without a stream (this one) completes the futures at once;
// the errors arrive on them, as they do from the Write stream.
TEST(Delivery, AsyncWritesCompleteTheirFuturesWithTheResultOrTheError) {
  auto transport = std::make_shared<FakeTransport>(cast::Identity{"writer", "vision", false});
  cast::UnmanagedComponent component;
  component.bind(transport);
  std::future<cast::WriteResult> added = component.addAsync("a", number(1));
  std::future<cast::WriteResult> again = component.addAsync("a", number(2));
  std::future<cast::WriteResult> stale = component.overwriteAsync("a", number(3), "", 99);
  const cast::WriteResult first = added.get();
  EXPECT_EQ(first.revision, 1u);
  EXPECT_THROW(again.get(), cast::AlreadyExistsError);
  EXPECT_THROW(stale.get(), cast::ConsistencyError);
  EXPECT_EQ(component.overwriteAsync("a", number(4), "", first.version).get().version, first.version + 1);
  EXPECT_EQ(component.get<Int64Value>("a").value(), 4);
  component.close();
}

}  // namespace
