// The lock calls and the LockGuard against an in-memory transport: scope,
// nesting, moves, release, failed unlocks, timeouts and tryLock.
#include <gtest/gtest.h>

#include <chrono>
#include <string>

#include "bound_component.h"
#include "cast/component.h"

namespace {

using namespace std::chrono_literals;
using cast::LockMode;
using cast::testing::Bound;
using cast::testing::counter;

// A bound component with an entry e1 to lock; depth(id) is how many times
// the fake server counts the component's lock of that entry.
struct WithEntry : Bound {
  WithEntry() { component.add("e1", counter("a", 1)); }
  auto depth(const std::string& id = "e1") const { return transport->lockDepth("vision", id); }
};

TEST(Component, LockGuardUnlocksAtTheEndOfItsScope) {
  WithEntry b;
  {
    cast::LockGuard guard = b.component.lock("e1", LockMode::ODR);
    EXPECT_TRUE(guard.held());
    EXPECT_EQ(guard.depth(), 1u);
    EXPECT_EQ(guard.address(), (cast::WorkingMemoryAddress{"e1", "vision"}));
    EXPECT_EQ(b.transport->lastLockMode, LockMode::ODR);
    EXPECT_EQ(b.depth(), 1u);
  }
  EXPECT_EQ(b.depth(), 0u);
}

TEST(Component, LockGuardsNestAndMove) {
  WithEntry b;
  cast::LockGuard outer = b.component.lock("e1");
  {
    cast::LockGuard inner = b.component.lock("e1");
    EXPECT_EQ(inner.depth(), 2u);
    cast::LockGuard moved = std::move(inner);
    EXPECT_FALSE(inner.held());  // NOLINT(bugprone-use-after-move): checking the moved-from state
    EXPECT_TRUE(moved.held());
    EXPECT_EQ(b.depth(), 2u);
  }
  EXPECT_EQ(b.depth(), 1u);
  EXPECT_EQ(b.transport->calls["unlock"], 1);
  outer.unlock();
  EXPECT_FALSE(outer.held());
  outer.unlock();  // idempotent
  EXPECT_EQ(b.transport->calls["unlock"], 2);
  EXPECT_EQ(b.depth(), 0u);
}

TEST(Component, MoveAssignmentReleasesTheOldLock) {
  WithEntry b;
  b.component.add("e2", counter("a", 1));
  cast::LockGuard g = b.component.lock("e1");
  g = b.component.lock("e2");
  EXPECT_EQ(b.depth(), 0u);
  EXPECT_EQ(b.depth("e2"), 1u);
}

TEST(Component, ReleasedGuardLeavesTheLockHeld) {
  WithEntry b;
  {
    cast::LockGuard g = b.component.lock("e1");
    g.release();
  }
  EXPECT_EQ(b.depth(), 1u);
  EXPECT_EQ(b.component.unlock("e1"), 0u);
}

TEST(Component, AGuardWhoseUnlockFailsDoesNotThrowFromItsDestructor) {
  WithEntry b;
  {
    cast::LockGuard g = b.component.lock("e1");
    b.component.deleteEntry("e1");  // deleting releases the lock: the guard's unlock then fails
  }
  SUCCEED();
}

TEST(Component, ExplicitUnlockOfAGuardReportsFailure) {
  WithEntry b;
  cast::LockGuard g = b.component.lock("e1");
  b.component.deleteEntry("e1");
  EXPECT_THROW(g.unlock(), cast::LockedError);
  EXPECT_FALSE(g.held());
}

TEST(Component, LockTimeoutIsTheCallsDeadline) {
  WithEntry b;
  { auto g = b.component.lock("e1", LockMode::O, "", 250ms); }
  EXPECT_EQ(b.transport->lastLockTimeout, std::optional<std::chrono::milliseconds>(250ms));
  EXPECT_FALSE(b.transport->lastLockNoWait);
  { auto g = b.component.lock("e1"); }
  EXPECT_EQ(b.transport->lastLockTimeout, std::nullopt);  // no timeout: wait forever
  b.transport->lockedByOther.insert("vision/e1");
  EXPECT_THROW(b.component.lock("e1", LockMode::O, "", 10ms), cast::DeadlineExceededError);
}

TEST(Component, TryLockMapsLockedToFalse) {
  WithEntry b;
  EXPECT_TRUE(b.component.tryLock("e1"));
  EXPECT_TRUE(b.transport->lastLockNoWait);
  b.component.unlock("e1");
  b.transport->lockedByOther.insert("vision/e1");
  EXPECT_FALSE(b.component.tryLock("e1"));
}

}  // namespace
