// Hello under test: a real CAST system for the test (cast/testing.h), GoogleTest to run it.
#include "hello.h"

#include <gtest/gtest.h>

#include "cast/testing.h"

using examples::hello::Greeting;

TEST(Hello, AddsItsGreetingsAndStopsOnceItSawThemAll) {
  cast::testing::LocalSystem system({"greetings"});
  auto& greetings = system.collectChanges({cast::globalTypeFilter<Greeting>()});
  auto& hello = system.run<Hello>("hello", "greetings", cast::Args::fromJson(R"({"count": 2})"));

  EXPECT_EQ(hello.join(), 0);  // it stops by itself after seeing its two greetings
  auto changes = greetings.waitForCount(2);
  EXPECT_EQ(changes[0].sourceComponent(), "hello");
  EXPECT_EQ(system.assertEntry<Greeting>("greetings", changes[1].id()).value.text(), "hello 1");
}

TEST(Hello, StopsOnceItSawAsManyGreetingsAsItWasToldOfAnyone) {
  cast::testing::LocalSystem system({"greetings"});
  Hello& hello = system.bind<Hello>("hello", "greetings");  // stepped: the test calls its hooks
  hello.configure(cast::Args::fromJson(R"({"count": 1})"));
  hello.start();  // no run(): it adds nothing itself
  Greeting greeting;
  greeting.set_text("hello from a test");
  system.actAs("visitor", "greetings").add("visit", greeting);
  cast::testing::waitFor([&] { return !hello.running(); }, std::chrono::seconds(10), "hello to ask to stop");
}
