// The component API against an in-memory transport: id generation, copy
// semantics, schema registration, change delivery and tasks (the lock guard:
// lock_guard_test.cc).
#include <gtest/gtest.h>

#include <atomic>
#include <regex>
#include <set>
#include <thread>

#include "cast/component.h"
#include "cast_fidelity.pb.h"
#include "cast_testing.pb.h"
#include "bound_component.h"
#include "fake_transport.h"
#include "unit_types.pb.h"

namespace {

using namespace std::chrono_literals;
using cast::LockMode;
using cast::Operation;
using cast::testing::Bound;
using cast::testing::Counter;
using cast::testing::counter;
using cast::testing::FakeTransport;
using cast::testing::Pose;

// ------------------------------------------------------------ identity, ids

TEST(Component, BindTakesTheIdentityAndStartsTheSession) {
  Bound b("segmenter", "vision");
  EXPECT_EQ(b.component.componentId(), "segmenter");
  EXPECT_EQ(b.component.subarchitecture(), "vision");
  EXPECT_FALSE(b.component.privileged());
  EXPECT_EQ(b.transport->sessionLanguage, "cpp");
  EXPECT_EQ(b.transport->sessionKind, "unmanaged");
  EXPECT_EQ(b.transport->reportedState(), cast::ComponentState::Starting);
  b.component.setState(cast::ComponentState::Running);
  EXPECT_EQ(b.transport->reportedState(), cast::ComponentState::Running);
}

TEST(Component, UnboundUseSaysHowToRunIt) {
  cast::UnmanagedComponent c;
  try {
    c.add("x", counter("a", 1));
    FAIL() << "no error";
  } catch (const cast::CastError& e) {
    EXPECT_NE(e.message().find("CAST_COMPONENT_MAIN"), std::string::npos) << e.message();
  }
  EXPECT_THROW(c.newId(), cast::CastError);
}

TEST(Component, NewIdsAreUniqueAndNamedAfterTheComponent) {
  Bound b("segmenter");
  std::set<std::string> ids;
  const std::regex shape("segmenter:[0-9a-f]{6}:[0-9]+");
  for (int i = 0; i < 1000; ++i) {
    std::string id = b.component.newId();
    EXPECT_TRUE(std::regex_match(id, shape)) << id;
    ids.insert(id);
  }
  EXPECT_EQ(ids.size(), 1000u);
}

TEST(Component, NewIdsAreUniqueAcrossThreads) {
  Bound b;
  std::mutex mu;
  std::set<std::string> ids;
  std::vector<std::thread> threads;
  for (int t = 0; t < 4; ++t) {
    threads.emplace_back([&] {
      for (int i = 0; i < 500; ++i) {
        auto id = b.component.newId();
        std::lock_guard<std::mutex> lock(mu);
        ids.insert(id);
      }
    });
  }
  for (auto& t : threads) t.join();
  EXPECT_EQ(ids.size(), 2000u);
}

TEST(Component, NewIdsDifferBetweenRestartsOfTheSameComponent) {
  // Two bindings of the same component id (a restart) must not reuse ids:
  // the counter starts again, so the random part has to differ.
  std::set<std::string> prefixes;
  for (int i = 0; i < 20; ++i) {
    Bound b("segmenter");
    std::string id = b.component.newId();
    prefixes.insert(id.substr(0, id.rfind(':')));
  }
  EXPECT_GE(prefixes.size(), 19u);  // 20 draws from 2^24: a collision is a one-in-40,000 event
}

// ------------------------------------------------------------ copies

TEST(Component, AWriteCopiesTheValue) {
  Bound b;
  Counter value = counter("a", 1);
  b.component.add("e1", value);
  value.set_value(99);  // after the write: must not reach the WM
  EXPECT_EQ(b.component.get<Counter>("e1").value(), 1);
}

TEST(Component, AReadReturnsAFreshCopy) {
  Bound b;
  b.component.add("e1", counter("a", 1));
  Counter first = b.component.get<Counter>("e1");
  first.set_value(42);
  EXPECT_EQ(b.component.get<Counter>("e1").value(), 1);

  auto entry = b.component.getEntry<Counter>("e1");
  entry.value.set_writer("changed");
  EXPECT_EQ(b.component.getEntry<Counter>("e1").value.writer(), "a");

  auto all = b.component.getAll<Counter>();
  ASSERT_EQ(all.size(), 1u);
  all[0].value.set_value(7);
  EXPECT_EQ(b.component.getAll<Counter>()[0].value.value(), 1);
}

TEST(Component, ReadingWithTheWrongTypeNamesBothTypesAndTheSubarchitecture) {
  Bound b;
  b.component.add("e1", counter("a", 1));
  try {
    b.component.get<Pose>("e1");
    FAIL() << "no error";
  } catch (const cast::InvalidArgumentError& e) {
    // Word for word Python's message.
    EXPECT_EQ(e.message(),
              "entry 'e1' in subarchitecture 'vision' has type cast.testing.Counter, not cast.testing.Pose: read it "
              "with the right class");
  }
}

TEST(Component, EntryMetadata) {
  Bound b("writer", "vision");
  b.component.add("e1", counter("a", 1));
  b.component.overwrite("e1", counter("a", 2));
  auto e = b.component.getEntry<Counter>("e1");
  EXPECT_EQ(e.id(), "e1");
  EXPECT_EQ(e.address.subarchitecture, "vision");
  EXPECT_EQ(e.type, "cast.testing.Counter");
  EXPECT_EQ(e.version, 1u);
  EXPECT_EQ(e.author, "writer");
  EXPECT_EQ(e.value.value(), 2);
}

TEST(Component, WritesGoToTheOwnSaUnlessGiven) {
  Bound b("c", "vision");
  b.component.add("e1", counter("a", 1));
  b.component.add("e1", counter("a", 2), "language");
  EXPECT_TRUE(b.component.exists("e1"));
  EXPECT_EQ(b.component.get<Counter>("e1", "language").value(), 2);
  EXPECT_EQ(b.component.get<Counter>("e1", "vision").value(), 1);
  b.component.deleteEntry("e1");
  EXPECT_FALSE(b.component.exists("e1"));
  EXPECT_TRUE(b.component.exists("e1", "language"));
}

TEST(Component, ExpectedVersionIsPassedOn) {
  Bound b;
  b.component.add("e1", counter("a", 1));
  EXPECT_THROW(b.component.overwrite("e1", counter("a", 2), "", 5u), cast::ConsistencyError);
  EXPECT_EQ(b.component.overwrite("e1", counter("a", 2), "", 0u).version, 1u);
  EXPECT_THROW(b.component.deleteEntry("e1", "", 0u), cast::ConsistencyError);
  EXPECT_NO_THROW(b.component.deleteEntry("e1", "", 1u));
}

TEST(Component, BatchSerialisesEveryValueAtOnce) {
  Bound b;
  Counter one = counter("a", 1);
  Counter two = counter("a", 2);
  auto results = b.component.batch({cast::BatchWrite::add("x", one), cast::BatchWrite::add("y", two),
                                    cast::BatchWrite::deleteEntry("x")});
  ASSERT_EQ(results.size(), 3u);
  ASSERT_EQ(b.transport->batches.size(), 1u);
  EXPECT_EQ(b.transport->batches[0][0].type, "cast.testing.Counter");
  EXPECT_EQ(b.transport->batches[0][2].type, "");
  EXPECT_TRUE(b.component.batch({}).empty());
  cast::BatchWrite bad{Operation::Add, "z", nullptr, std::nullopt};
  EXPECT_THROW(b.component.batch({bad}), cast::InvalidArgumentError);
}

// ------------------------------------------------------------ schemas

TEST(Component, RegistersEachTypesSchemaOnceBeforeItsFirstWrite) {
  Bound b;
  EXPECT_TRUE(b.transport->registered.empty());
  b.component.add("e1", counter("a", 1));
  ASSERT_EQ(b.transport->registered.size(), 1u);
  EXPECT_EQ(b.transport->registered[0].file(0).name(), "cast_testing.proto");
  b.component.add("e2", counter("a", 2));
  b.component.overwrite("e1", counter("a", 3));
  EXPECT_EQ(b.transport->registered.size(), 1u);
  Pose pose;
  b.component.add("p1", pose);
  EXPECT_EQ(b.transport->registered.size(), 2u);
}

TEST(Component, RegistersATypeWithTheServerOfEachSaItIsWrittenToAndNoOther) {
  Bound b;
  b.component.add("e1", counter("a", 1));
  b.component.add("e1", counter("a", 1), "motor");
  b.component.overwrite("e1", counter("a", 2), "motor");
  Counter c3 = counter("a", 3);
  b.component.batch({cast::BatchWrite{Operation::Add, "e2", &c3, std::nullopt}}, "motor");
  EXPECT_EQ(b.transport->registeredSas, (std::vector<std::string>{"vision", "motor"}));
  Pose pose;
  b.component.add("p1", pose, "motor");
  EXPECT_EQ(b.transport->registeredSas, (std::vector<std::string>{"vision", "motor", "motor"}));
}

TEST(Component, RegistersEveryFileATypeImports) {
  Bound b;
  cast::unittest::Observation obs;
  b.component.add("o1", obs);
  ASSERT_EQ(b.transport->registered.size(), 1u);
  std::vector<std::string> names;
  for (const auto& f : b.transport->registered[0].file()) names.push_back(f.name());
  // Dependencies first, the type's own file last.
  EXPECT_EQ(names, (std::vector<std::string>{"google/protobuf/timestamp.proto", "cast_testing.proto",
                                             "unit_types.proto"}));
}

// ------------------------------------------------------------ watching

TEST(Component, OnChangeDeliversOnTheDispatcherInOrder) {
  Bound b("c", "vision");
  std::vector<std::uint64_t> revisions;
  std::atomic<bool> onDispatcher{true};
  auto handle = b.component.onChange(cast::localTypeFilter<Counter>(), [&](const cast::WorkingMemoryChange& c) {
    revisions.push_back(c.revision());
    if (!b.component.onDispatcherThread()) onDispatcher = false;
  });
  for (int i = 0; i < 100; ++i) b.component.add("e" + std::to_string(i), counter("a", i));
  Pose other;
  b.component.add("p", other);  // another type: not delivered
  ASSERT_TRUE(b.component.drain());
  ASSERT_EQ(revisions.size(), 100u);
  for (size_t i = 1; i < revisions.size(); ++i) EXPECT_LT(revisions[i - 1], revisions[i]);
  EXPECT_TRUE(onDispatcher);
  EXPECT_TRUE(handle.active());
}

TEST(Component, ChangesCarryTheEntryOnlyWhenAskedAndItIsACopy) {
  Bound b;
  std::vector<cast::WorkingMemoryChange> changes;
  b.component.onChange(cast::addressFilter("e1", {Operation::Add}).withEntry(),
                       [&](const cast::WorkingMemoryChange& c) { changes.push_back(c); });
  b.component.onChange(cast::addressFilter("e1", {Operation::Overwrite}),
                       [&](const cast::WorkingMemoryChange& c) { changes.push_back(c); });
  b.component.add("e1", counter("a", 5));
  b.component.overwrite("e1", counter("a", 6));
  ASSERT_TRUE(b.component.drain());
  ASSERT_EQ(changes.size(), 2u);
  ASSERT_TRUE(changes[0].hasEntry());
  auto entry = changes[0].entry<Counter>();
  EXPECT_EQ(entry.value.value(), 5);
  EXPECT_EQ(changes[0].operation(), Operation::Add);
  EXPECT_EQ(changes[0].sourceComponent(), "comp");
  EXPECT_FALSE(changes[1].hasEntry());
  EXPECT_THROW(changes[1].entry<Counter>(), cast::InvalidArgumentError);
}

TEST(Component, LocalFiltersAreResolvedBeforeTheyAreSent) {
  Bound b("c", "motor");
  std::atomic<int> hits{0};
  b.component.onChange(cast::localTypeFilter<Counter>(), [&](const cast::WorkingMemoryChange&) { ++hits; });
  b.component.add("e1", counter("a", 1));             // motor: matches
  b.component.add("e1", counter("a", 1), "vision");   // other SA: does not
  ASSERT_TRUE(b.component.drain());
  EXPECT_EQ(hits.load(), 1);
}

TEST(Component, CancelStopsDeliveryAndDropsQueuedChanges) {
  Bound b;
  std::atomic<int> hits{0};
  std::atomic<bool> release{false};
  cast::WatchHandle handle;
  handle = b.component.onChange(cast::localTypeFilter<Counter>(), [&](const cast::WorkingMemoryChange&) {
    ++hits;
    while (!release) std::this_thread::sleep_for(1ms);
  });
  b.component.add("e1", counter("a", 1));  // the first callback blocks the dispatcher
  while (hits.load() == 0) std::this_thread::sleep_for(1ms);
  for (int i = 2; i < 10; ++i) b.component.add("e" + std::to_string(i), counter("a", i));  // queued
  handle.cancel();
  release = true;
  ASSERT_TRUE(b.component.drain());
  EXPECT_EQ(hits.load(), 1);
  EXPECT_FALSE(handle.active());
  EXPECT_EQ(b.transport->cancelled, std::vector<std::uint32_t>{handle.watchId()});
  handle.cancel();  // idempotent
  EXPECT_EQ(b.transport->cancelled.size(), 1u);
}

TEST(Component, OnChangeNeedsAFilterAndACallback) {
  Bound b;
  EXPECT_THROW(b.component.onChange(std::vector<cast::ChangeFilter>{}, [](const cast::WorkingMemoryChange&) {}),
               cast::InvalidArgumentError);
  EXPECT_THROW(b.component.onChange(cast::localTypeFilter<Counter>(), nullptr), cast::InvalidArgumentError);
}

TEST(Component, ARefusedWatchLeavesNoCallbackBehind) {
  Bound b;
  b.transport->failNextWatch = true;
  std::atomic<int> hits{0};
  EXPECT_THROW(b.component.onChange(cast::localTypeFilter<Counter>(), [&](const auto&) { ++hits; }),
               cast::InvalidArgumentError);
  auto ok = b.component.onChange(cast::localTypeFilter<Counter>(), [&](const auto&) { ++hits; });
  b.component.add("e1", counter("a", 1));
  ASSERT_TRUE(b.component.drain());
  EXPECT_EQ(hits.load(), 1);
  EXPECT_EQ(ok.watchId(), 2u);
}

class WatchFailedRecorder : public cast::UnmanagedComponent {
 public:
  void watchFailed(const cast::CastError& error) override {
    name = error.name();
    onDispatcher = onDispatcherThread();
  }
  std::string name;
  bool onDispatcher = false;
};

TEST(Component, AStreamFailureReachesWatchFailedAndTheHandles) {
  auto transport = std::make_shared<FakeTransport>(cast::Identity{"c", "vision", false});
  WatchFailedRecorder c;
  c.bind(transport);
  auto handle = c.onChange(cast::localTypeFilter<Counter>(), [](const auto&) {});
  EXPECT_EQ(handle.error(), nullptr);
  transport->failWatches(std::make_shared<cast::HistoryExpiredError>("fell behind"));
  ASSERT_TRUE(c.drain());
  EXPECT_EQ(c.name, "HistoryExpiredError");
  EXPECT_TRUE(c.onDispatcher);
  ASSERT_NE(handle.error(), nullptr);
  EXPECT_STREQ(handle.error()->name(), "HistoryExpiredError");
  c.close();
}

// ------------------------------------------------------------ stopping

TEST(Component, RequestStopWakesWaitForStop) {
  Bound b;
  EXPECT_TRUE(b.component.running());
  EXPECT_FALSE(b.component.waitForStop(10ms));
  std::thread t([&] {
    std::this_thread::sleep_for(20ms);
    b.component.requestStop();
  });
  EXPECT_TRUE(b.component.waitForStop(5000ms));
  EXPECT_FALSE(b.component.running());
  t.join();
}

TEST(Component, CloseEndsTheSessionOnceAndRefusesLaterCalls) {
  Bound b;
  b.component.close();
  EXPECT_TRUE(b.transport->closed);
  EXPECT_THROW(b.component.add("e1", counter("a", 1)), cast::CastError);
  b.component.close();
}

// ------------------------------------------------------------ tasks

class Tasker : public cast::ManagedComponent {
 public:
  void taskAdopted(const cast::Task& task) override {
    std::lock_guard<std::mutex> lock(mu);
    adopted.push_back(task);
    onDispatcher = onDispatcher && onDispatcherThread();
  }
  void taskRejected(const cast::Task& task) override {
    std::lock_guard<std::mutex> lock(mu);
    rejected.push_back(task);
  }
  std::mutex mu;
  std::vector<cast::Task> adopted;
  std::vector<cast::Task> rejected;
  bool onDispatcher = true;
};

TEST(ManagedComponent, DecisionsReachTheHooksOnTheDispatcher) {
  auto transport = std::make_shared<FakeTransport>(cast::Identity{"planner", "vision", false});
  Tasker t;
  t.bind(transport);
  EXPECT_EQ(transport->sessionKind, "managed");
  cast::Task proposed = t.proposeTask("look", counter("x", 3), 7);
  EXPECT_EQ(proposed.state(), cast::TaskState::Waiting);
  EXPECT_EQ(proposed.priority(), 7);
  t.proposeTask("reject-me");
  ASSERT_TRUE(t.drain());
  ASSERT_EQ(t.adopted.size(), 1u);
  EXPECT_EQ(t.adopted[0].name(), "look");
  EXPECT_EQ(t.adopted[0].taskId(), proposed.taskId());
  ASSERT_TRUE(t.adopted[0].data<Counter>().has_value());
  EXPECT_EQ(t.adopted[0].data<Counter>()->value(), 3);
  EXPECT_THROW(t.adopted[0].data<Pose>(), cast::InvalidArgumentError);
  ASSERT_EQ(t.rejected.size(), 1u);
  EXPECT_FALSE(t.rejected[0].hasData());
  EXPECT_EQ(t.rejected[0].data<Counter>(), std::nullopt);
  EXPECT_TRUE(t.onDispatcher);

  t.taskComplete(t.adopted[0], cast::TaskOutcome::Failed, "no luck");
  t.retractTask("task-9");
  ASSERT_EQ(transport->completed.size(), 1u);
  EXPECT_EQ(transport->completed[0].first, proposed.taskId());
  EXPECT_EQ(transport->completed[0].second, cast::TaskOutcome::Failed);
  EXPECT_EQ(transport->retracted, std::vector<std::string>{"task-9"});
  // The payload's schema was registered like an entry's.
  EXPECT_EQ(transport->registered.size(), 1u);
  t.close();
}

}  // namespace
