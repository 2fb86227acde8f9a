// The first contact of a launched component (connect_window.h): which
// failures are asked again, when the window ends, and what the runner then
// says. Runs on a clock of its own: the waits only move that clock forward.
#include <gtest/gtest.h>

#include <chrono>
#include <functional>
#include <string>
#include <vector>

#include "cast/runner.h"
#include "connect_window.h"

namespace {

using cast::detail::Millis;

// A clock that stands still except when the code under test waits.
struct FakeClock {
  std::chrono::steady_clock::time_point t{};
  std::vector<Millis> waits;
  bool stopAtWait = false;

  cast::detail::ConnectClock clock() {
    cast::detail::ConnectClock c;
    c.now = [this] { return t; };
    c.wait = [this](Millis d) {
      waits.push_back(d);
      t += d;
      return stopAtWait;
    };
    return c;
  }
};

const cast::Logger kLog("cast.run.test");

// An attempt that fails with `failures` (in order), then answers 42.
std::function<int()> failing(std::vector<std::function<void()>> failures, int* calls) {
  return [failures, calls]() -> int {
    const auto i = static_cast<std::size_t>((*calls)++);
    if (i < failures.size()) failures[i]();
    return 42;
  };
}

void unavailable() { throw cast::UnavailableError("server unavailable (connection refused)"); }
void deadline() { throw cast::DeadlineExceededError("Deadline Exceeded"); }

TEST(ConnectWindow, IsTwentySecondsAsInPython) { EXPECT_EQ(cast::kConnectWindow, std::chrono::seconds(20)); }

TEST(ConnectWindow, OnlyAServerThatIsDownStartingOrBusyIsAskedAgain) {
  EXPECT_TRUE(cast::detail::connectRetried("UNAVAILABLE"));
  EXPECT_TRUE(cast::detail::connectRetried("DEADLINE_EXCEEDED"));
  for (const char* code : {"UNAUTHENTICATED", "INVALID_ARGUMENT", "PERMISSION_DENIED", "INTERNAL", "UNKNOWN"}) {
    EXPECT_FALSE(cast::detail::connectRetried(code)) << code;
  }
}

TEST(ConnectWindow, AServerThatAnswersLateIsAskedAgainWithBackoff) {
  FakeClock fake;
  int calls = 0;
  const int got = cast::detail::connectWithin<int>("127.0.0.1:4711", false, cast::kConnectWindow,
                                                   failing({unavailable, deadline, unavailable}, &calls),
                                                   fake.clock(), kLog);
  EXPECT_EQ(got, 42);
  EXPECT_EQ(calls, 4);
  ASSERT_EQ(fake.waits.size(), 3u);
  EXPECT_LT(fake.waits.front(), fake.waits.back()) << "the waits grow";
}

TEST(ConnectWindow, OtherErrorsFailAtOnce) {
  FakeClock fake;
  int calls = 0;
  auto refused = [] { throw cast::UnauthenticatedError("token signature does not match"); };
  EXPECT_THROW(cast::detail::connectWithin<int>("h:1", false, cast::kConnectWindow, failing({refused}, &calls),
                                                fake.clock(), kLog),
               cast::UnauthenticatedError);
  EXPECT_EQ(calls, 1);
  EXPECT_TRUE(fake.waits.empty());
}

TEST(ConnectWindow, GivesUpWhenTheWindowHasPassedSayingWhereForHowLongAndWhatToCheck) {
  FakeClock fake;
  int calls = 0;
  std::vector<std::function<void()>> forever(1000, unavailable);
  try {
    cast::detail::connectWithin<int>("127.0.0.1:4711", true, cast::kConnectWindow, failing(forever, &calls),
                                     fake.clock(), kLog);
    FAIL() << "no error";
  } catch (const cast::UnavailableError& e) {
    EXPECT_EQ(e.message(),
              "no CAST system answered at 127.0.0.1:4711 within 20 s (CAST_ENDPOINT, spoken to with TLS): check "
              "that the system is running and that CAST_ENDPOINT and CAST_TLS_* are its address and TLS settings "
              "(last error: server unavailable (connection refused))");
  }
  EXPECT_GT(calls, 2) << "asked again before giving up";
  EXPECT_LT(calls, 100) << "the backoff grows: the window is not spent knocking";
  EXPECT_GE(fake.t - std::chrono::steady_clock::time_point{}, cast::kConnectWindow);
}

TEST(ConnectWindow, AnEmptyWindowGivesUpAfterTheFirstTry) {
  FakeClock fake;
  int calls = 0;
  EXPECT_THROW(cast::detail::connectWithin<int>("h:1", false, Millis(0), failing({unavailable}, &calls),
                                                fake.clock(), kLog),
               cast::UnavailableError);
  EXPECT_EQ(calls, 1);
}

TEST(ConnectWindow, AStopRequestEndsTheAsking) {
  FakeClock fake;
  fake.stopAtWait = true;
  int calls = 0;
  try {
    cast::detail::connectWithin<int>("h:1", false, cast::kConnectWindow, failing({unavailable}, &calls),
                                     fake.clock(), kLog);
    FAIL() << "no error";
  } catch (const cast::CastError& e) {
    EXPECT_EQ(e.code(), "CANCELLED");
  }
  EXPECT_EQ(calls, 1);
}

TEST(ConnectWindow, GaveUpSaysTheWindowAsPythonDoes) {
  EXPECT_NE(cast::detail::connectGaveUp("h:1", Millis(1500), false, "x").find("within 1.5 s (CAST_ENDPOINT, "
                                                                                 "spoken to in plaintext)"),
            std::string::npos);
}

}  // namespace
