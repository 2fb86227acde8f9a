// The start barrier in the runner (docs/client-protocol.md, "Start-up"): a
// component `cast run` launched (CAST_START_BARRIER=1) reports STARTED after
// start() and begins run() only once the barrier is released; one started
// any other way runs at once. Against the in-memory transport's barrier.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <functional>
#include <future>
#include <thread>

#include "cast/runner.h"
#include "fake_transport.h"

namespace {

using namespace std::chrono_literals;
using cast::ComponentState;
using cast::testing::FakeTransport;

class Recorder : public cast::UnmanagedComponent {
 public:
  void start() override { ++starts; }
  void run() override {
    ++runs;
    waitForStop();
  }
  void stop() override { ++stops; }

  std::atomic<int> starts{0};
  std::atomic<int> runs{0};
  std::atomic<int> stops{0};
};

// Polls `condition` for up to 5 s.
bool eventually(const std::function<bool()>& condition) {
  const auto until = std::chrono::steady_clock::now() + 5s;
  while (!condition()) {
    if (std::chrono::steady_clock::now() > until) return false;
    std::this_thread::sleep_for(5ms);
  }
  return true;
}

struct Rig {
  Rig() : transport(std::make_shared<FakeTransport>(cast::Identity{"watcher", "b", false})) {}
  // Runs the component on its own thread, as the runner's main() would (no signal handlers).
  std::future<int> run(bool startBarrier) {
    return std::async(std::launch::async, [this, startBarrier] {
      return cast::runComponent(component, transport, cast::Args(), false, startBarrier);
    });
  }
  std::shared_ptr<FakeTransport> transport;
  Recorder component;
};

TEST(StartBarrier, RunWaitsForTheReleaseAndTheStateReportedMeanwhileIsStarted) {
  Rig rig;
  rig.transport->holdBarrier();
  auto exit = rig.run(true);
  ASSERT_TRUE(eventually([&] { return rig.transport->awaitRunCount() > 0; }));
  EXPECT_EQ(rig.transport->stateAtAwaitRun, ComponentState::Started) << "STARTED is reported before the wait";
  std::this_thread::sleep_for(150ms);
  EXPECT_EQ(rig.component.starts, 1);
  EXPECT_EQ(rig.component.runs, 0) << "run() began before the barrier was released";
  EXPECT_EQ(rig.transport->reportedState(), ComponentState::Started);

  rig.transport->releaseBarrier();
  ASSERT_TRUE(eventually([&] { return rig.component.runs == 1; }));
  EXPECT_EQ(rig.transport->reportedState(), ComponentState::Running);
  rig.component.requestStop();
  EXPECT_EQ(exit.get(), 0);
  EXPECT_EQ(rig.component.stops, 1);
  EXPECT_EQ(rig.transport->awaitRunCalls, 1);
  // Each state was reported at once, STARTED before RUNNING.
  const std::vector<ComponentState> expected{ComponentState::Started, ComponentState::Running,
                                             ComponentState::Stopping};
  EXPECT_EQ(rig.transport->stateChanges, expected);
}

TEST(StartBarrier, WithoutTheBarrierRunFollowsStartAndAwaitRunIsNeverCalled) {
  Rig rig;
  rig.transport->holdBarrier();  // would hold run() back if it were asked
  auto exit = rig.run(false);
  ASSERT_TRUE(eventually([&] { return rig.component.runs == 1; }));
  rig.component.requestStop();
  EXPECT_EQ(exit.get(), 0);
  EXPECT_EQ(rig.transport->awaitRunCalls, 0);
  EXPECT_EQ(std::count(rig.transport->stateChanges.begin(), rig.transport->stateChanges.end(),
                       ComponentState::Started),
            0);
}

TEST(StartBarrier, OnStartedComesOnceBeforeRunAndAlsoWhenTheComponentStopsAtTheBarrier) {
  Rig rig;
  std::atomic<int> called{0};
  std::atomic<int> runsWhenCalled{-1};
  auto exit = std::async(std::launch::async, [&] {
    return cast::runComponent(rig.component, rig.transport, cast::Args(), false, false, [&] {
      runsWhenCalled = rig.component.runs.load();
      ++called;
    });
  });
  ASSERT_TRUE(eventually([&] { return rig.component.runs == 1; }));
  EXPECT_EQ(called, 1);
  EXPECT_EQ(runsWhenCalled, 0) << "onStarted came after run() began";
  rig.component.requestStop();
  EXPECT_EQ(exit.get(), 0);
  EXPECT_EQ(called, 1);

  // Stopped at the barrier, run() never begins: onStarted still comes, once, so nobody waits for ever.
  Rig held;
  held.transport->holdBarrier();
  std::atomic<int> heldCalls{0};
  auto heldExit = std::async(std::launch::async, [&] {
    return cast::runComponent(held.component, held.transport, cast::Args(), false, true, [&] { ++heldCalls; });
  });
  ASSERT_TRUE(eventually([&] { return held.transport->awaitRunCount() > 0; }));
  EXPECT_EQ(heldCalls, 0);
  held.component.requestStop();
  EXPECT_EQ(heldExit.get(), 0);
  EXPECT_EQ(heldCalls, 1);
  EXPECT_EQ(held.component.runs, 0);
}

TEST(StartBarrier, AReleasedBarrierLetsRunBeginAtOnce) {
  // A component that joins later or was restarted finds the barrier released.
  Rig rig;
  auto exit = rig.run(true);
  ASSERT_TRUE(eventually([&] { return rig.component.runs == 1; }));
  rig.component.requestStop();
  EXPECT_EQ(exit.get(), 0);
  EXPECT_EQ(rig.transport->awaitRunCalls, 1);
}

TEST(StartBarrier, AStopRequestedWhileWaitingSkipsRunAndCallsStopOnce) {
  Rig rig;
  rig.transport->holdBarrier();
  auto exit = rig.run(true);
  ASSERT_TRUE(eventually([&] { return rig.transport->awaitRunCount() > 0; }));
  rig.component.requestStop();
  ASSERT_EQ(exit.wait_for(5s), std::future_status::ready) << "the wait did not see the stop request";
  EXPECT_EQ(exit.get(), 0);
  EXPECT_EQ(rig.component.runs, 0);
  EXPECT_EQ(rig.component.stops, 1);
}

TEST(StartBarrier, ARefusedWaitFailsTheStartLikeAFailingHook) {
  Rig rig;
  rig.transport->awaitRunError = std::make_shared<cast::PermissionDeniedError>("not yours to wait for");
  auto exit = rig.run(true);
  ASSERT_EQ(exit.wait_for(5s), std::future_status::ready);
  EXPECT_EQ(exit.get(), 1);
  EXPECT_EQ(rig.component.runs, 0);
  EXPECT_EQ(rig.component.stops, 1);
}

}  // namespace
