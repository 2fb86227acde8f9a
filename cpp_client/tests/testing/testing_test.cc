// cast::testing, the kit for component authors (cast/testing.h), against the
// repository's own `cast serve` (CAST_SERVE, set by ctest): systems,
// components run and stepped, actors and their tasks, collected changes, the
// messages of failed expectations, a restart, and that no server is left
// behind after a failed test or a killed test process.
#include <google/protobuf/wrappers.pb.h>
#include <gtest/gtest.h>
#include <signal.h>
#include <unistd.h>

#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <memory>
#include <sstream>
#include <string>
#include <thread>

#include "cast/cast.h"
#include "cast/testing.h"

namespace {

using namespace std::chrono_literals;
using cast::testing::AssertionError;
using cast::testing::LocalSystem;
using google::protobuf::Int64Value;
using google::protobuf::StringValue;

Int64Value number(std::int64_t n) {
  Int64Value v;
  v.set_value(n);
  return v;
}

StringValue text(const std::string& s) {
  StringValue v;
  v.set_value(s);
  return v;
}

bool contains(const std::string& text, const std::string& part) { return text.find(part) != std::string::npos; }

// Counts to "to" in the entry "count" when an entry "go" appears; slow to start on purpose.
class Counter : public cast::UnmanagedComponent {
 public:
  void configure(const cast::Args& args) override { last_ = args.getInt("to", 3); }
  void start() override {
    std::this_thread::sleep_for(300ms);  // a watch registered late: run() must not hand it over before
    onChange(cast::addressFilter("go", {cast::Operation::Add}), [this](const cast::WorkingMemoryChange&) {
      cast::WriteResult result = add("count", number(0));
      for (std::int64_t n = 1; n <= last_; ++n) result = overwrite("count", number(n), "", result.version);
    });
  }
  void stop() override { stopped = true; }
  std::atomic<bool> stopped{false};

 private:
  std::int64_t last_ = 3;
};

class Broken : public cast::UnmanagedComponent {
 public:
  void start() override { throw std::runtime_error("no camera attached"); }
};

// The processes whose command line names `text` (the server's names its system's directory).
std::vector<int> processesNaming(const std::string& text) {
  std::vector<int> found;
  for (const auto& entry : std::filesystem::directory_iterator("/proc")) {
    const std::string name = entry.path().filename();
    if (name.find_first_not_of("0123456789") != std::string::npos) continue;
    std::ifstream stat(entry.path() / "stat");
    std::string line;
    std::getline(stat, line);
    const auto close = line.rfind(')');
    if (close == std::string::npos || line.substr(close + 2, 1) == "Z") continue;  // a zombie no longer runs
    std::ifstream cmdline(entry.path() / "cmdline");
    std::stringstream all;
    all << cmdline.rdbuf();
    if (contains(all.str(), text) && std::stoi(name) != ::getpid()) found.push_back(std::stoi(name));
  }
  return found;
}

// Runs this test binary's disabled helper `test` with `env` before it; its output and status.
std::pair<std::string, int> runHelper(const std::string& test, const std::string& env) {
  const std::string self = std::filesystem::read_symlink("/proc/self/exe");
  // exec: the helper replaces the shell, so its status is the helper's own.
  const std::string command = "exec env " + env + " '" + self +
                              "' --gtest_also_run_disabled_tests --gtest_filter=KitHelper.DISABLED_" + test + " 2>&1";
  FILE* pipe = ::popen(command.c_str(), "r");
  std::string output;
  char buffer[4096];
  for (std::size_t n; (n = std::fread(buffer, 1, sizeof buffer, pipe)) > 0;) output.append(buffer, n);
  const int status = ::pclose(pipe);
  return {output, status};
}

TEST(Kit, RunsAComponentAndHandsItOverOnceItsWatchesAreRegistered) {
  LocalSystem system({"vision", "language"});
  EXPECT_EQ(system.subarchitectures(), (std::vector<std::string>{"vision", "language"}));
  auto& counter = system.run<Counter>("counter", "vision", cast::Args::fromJson(R"({"to": 3})"));
  system.actAs("camera", "vision").add("go", text("now"));  // right away: start() slept first
  const auto entry = system.waitForEntry<Int64Value>("vision", "count", number(3));
  EXPECT_EQ(entry.author, "counter");
  EXPECT_EQ(counter.stop(), 0);
  EXPECT_TRUE(counter.component().stopped);
  EXPECT_FALSE(counter.running());

  auto& broken = system.run<Broken>("broken", "vision");
  EXPECT_EQ(broken.join(), 1);
}

TEST(Kit, StepsABoundComponentAndActsAsOthers) {
  LocalSystem system({"vision", "language"});
  auto& counter = system.bind<Counter>("counter", "vision");
  counter.configure(cast::Args::fromJson(R"({"to": 2})"));
  counter.start();
  auto& camera = system.actAs("camera", "vision");
  camera.add("go", text("now"));
  system.waitForEntry<Int64Value>("vision", "count", [](const Int64Value& v) { return v.value() == 2; });
  EXPECT_THROW(camera.add("note", text("hi"), "language"), cast::PermissionDeniedError);
  system.actAs("boss", "vision", true).add("order", text("go"), "language");
  EXPECT_EQ(system.assertEntry<StringValue>("language", "order").author, "boss");
  EXPECT_THROW(system.actAs("camera", "motor"), cast::InvalidArgumentError);

  // The launch contract of a process the test would start, here used by a script.
  const auto env = system.launchEnvironment("greeter", "language", cast::Args::fromJson(R"({"to": 1})"));
  EXPECT_EQ(env.at("CAST_ARGS"), R"({"to":1})");
  cast::ConnectOptions options;
  options.endpoint = env.at("CAST_ENDPOINT");
  options.token = env.at("CAST_TOKEN");
  auto greeter = cast::connect(options);
  EXPECT_EQ(greeter->componentId(), "greeter");
  EXPECT_EQ(greeter->subarchitecture(), "language");
}

TEST(Kit, ServesAConfigurationAndItsTaskManagers) {
  const std::string dir = ::testing::TempDir() + "kit-config";
  std::filesystem::create_directories(dir);
  std::ofstream(dir + "/tasks.yaml") << "system: tasks\nsubarchitectures:\n"
                                        "  ${SA:-vision}:\n    task_manager: {policy: exclusive}\n";
  cast::testing::SystemOptions options;
  options.config = dir + "/tasks.yaml";
  options.sets = {{"SA", "planning"}};
  LocalSystem system(options);
  EXPECT_EQ(system.name(), "tasks");
  EXPECT_EQ(system.subarchitectures(), std::vector<std::string>{"planning"});
  auto& planner = system.actAs("planner", "planning");
  const cast::Task first = planner.waitForDecision(planner.proposeTask("plan"));
  const cast::Task second = planner.waitForDecision(planner.proposeTask("plan again"));
  EXPECT_EQ(first.state(), cast::TaskState::Adopted);
  EXPECT_EQ(second.state(), cast::TaskState::Rejected);
  EXPECT_EQ(planner.decisions().size(), 2u);
  std::filesystem::remove_all(dir);
}

TEST(Kit, FailedExpectationsSayWhatWasSeen) {
  LocalSystem system({"vision"});
  auto& changes = system.collectChanges();
  system.actAs("counter", "vision").add("count", number(2));
  try {
    system.assertEntry<Int64Value>("vision", "count", number(3));
    FAIL() << "a wrong value passed";
  } catch (const AssertionError& e) {
    EXPECT_TRUE(contains(e.what(), "entry 'count' in subarchitecture 'vision' holds google.protobuf.Int64Value "
                                   "{value: 2} (version ")) << e.what();
    EXPECT_TRUE(contains(e.what(), "by counter), expected google.protobuf.Int64Value {value: 3}")) << e.what();
  }
  try {
    system.assertEntry<Int64Value>("vision", "counts");
    FAIL() << "a missing entry passed";
  } catch (const AssertionError& e) {
    EXPECT_TRUE(contains(e.what(), "no entry 'counts' in subarchitecture 'vision'; entries there: count "
                                   "(google.protobuf.Int64Value)")) << e.what();
  }
  try {
    system.assertEntry<StringValue>("vision", "count");
    FAIL() << "a wrong type passed";
  } catch (const AssertionError& e) {
    EXPECT_TRUE(contains(e.what(), "has type google.protobuf.Int64Value, not google.protobuf.StringValue")) << e.what();
  }
  try {
    system.waitForEntry<Int64Value>("vision", "count", number(3), 200ms);
    FAIL() << "waiting for a value that never came passed";
  } catch (const AssertionError& e) {
    EXPECT_TRUE(contains(e.what(), "timed out after 0.2 s waiting for entry 'count' in subarchitecture 'vision': "
                                   "entry 'count' in subarchitecture 'vision' holds")) << e.what();
  }
  changes.waitForCount(1);
  try {
    changes.waitForCount(2, 200ms);
    FAIL() << "a second change that never came passed";
  } catch (const AssertionError& e) {
    EXPECT_TRUE(contains(e.what(), "timed out after 0.2 s waiting for 2 changes; seen: 1 change:\n  ADD vision/count "
                                   "by counter (revision 1): google.protobuf.Int64Value")) << e.what();
  }
  try {
    cast::testing::waitFor([] { return false; }, 50ms, "three greetings", [] { return std::string("one greeting"); });
    FAIL() << "a condition that never held passed";
  } catch (const AssertionError& e) {
    EXPECT_STREQ(e.what(), "timed out after 0.05 s waiting for three greetings; seen: one greeting");
  }
}

TEST(Kit, RestartsTheServerEmpty) {
  LocalSystem system({"vision"});
  auto& camera = system.actAs("camera", "vision");
  camera.add("image", text("before"));
  system.restart();
  cast::testing::waitFor(
      [&] {
        try {
          camera.add("image", text("after"));
          return true;
        } catch (const cast::UnavailableError&) {
          return false;
        }
      },
      20s, "the actor writing to the restarted server");
  system.assertEntry<StringValue>("vision", "image", text("after"));
  EXPECT_TRUE(contains(system.output(), "listening on ")) << system.output();
}

TEST(Kit, LeavesNoServerAfterAFailedTestNorAKilledTestProcess) {
  std::string directory;
  try {
    LocalSystem system({"vision"});
    directory = system.directory();
    ASSERT_EQ(processesNaming(directory).size(), 1u);
    throw AssertionError("the test failed");
  } catch (const AssertionError&) {
  }
  EXPECT_TRUE(processesNaming(directory).empty());
  EXPECT_FALSE(std::filesystem::exists(directory));

  const auto [output, status] = runHelper("KillsItself", "");
  EXPECT_TRUE(WIFSIGNALED(status) && WTERMSIG(status) == SIGKILL) << output;
  const auto at = output.find("directory ");
  ASSERT_NE(at, std::string::npos) << output;
  const std::string killed = output.substr(at + 10, output.find('\n', at) - at - 10);
  cast::testing::waitFor([&] { return processesNaming(killed).empty(); }, 30s,
                         "the killed test process's server to end");
  std::filesystem::remove_all(killed);  // what a killed process cannot clean up itself
}

TEST(Kit, SaysWhatToInstallWhenThereIsNoServer) {
  const auto [output, status] = runHelper("ReportsAMissingServer", "CAST_SERVE=/no/such/cast");
  EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << output;
  EXPECT_TRUE(contains(output, "CAST_SERVE names /no/such/cast, which is not an executable file")) << output;
  const auto [bare, bareStatus] = runHelper("ReportsAMissingServer", "CAST_SERVE= PATH=/nonexistent");
  EXPECT_TRUE(WIFEXITED(bareStatus) && WEXITSTATUS(bareStatus) == 0) << bare;
  EXPECT_TRUE(contains(bare, "install it with `pip install cast-grpc`")) << bare;
}

// Helpers the tests above run as processes of their own (disabled otherwise).
TEST(KitHelper, DISABLED_KillsItself) {
  LocalSystem system({"vision"});
  std::printf("directory %s\n", system.directory().c_str());
  std::fflush(stdout);
  ::kill(::getpid(), SIGKILL);
}

TEST(KitHelper, DISABLED_ReportsAMissingServer) {
  try {
    LocalSystem system({"vision"});
    FAIL() << "a system started without a server";
  } catch (const cast::NotFoundError& e) {
    std::printf("refused: %s\n", e.message().c_str());
  }
}

}  // namespace
