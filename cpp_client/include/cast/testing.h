// A testing kit for components (CMake target cast::testing): a real CAST
// system for each test, and what a test does with it.
//
//   #include "cast/testing.h"
//
//   TEST(Counter, CountsToThree) {
//     cast::testing::LocalSystem system({"vision"});            // `cast serve` on a free port
//     auto& counter = system.run<Counter>("counter", "vision", cast::Args::fromJson(R"({"to": 3})"));
//     system.actAs("camera", "vision").add("go", text("now"));    // the test acting as another component
//     system.waitForEntry<Int64Value>("vision", "count", number(3));
//     EXPECT_EQ(counter.stop(), 0);
//   }                                                             // everything stopped, also when the test fails
//
// The system is the repository's own server, `cast serve`, started as a
// process on a port of 127.0.0.1 the kernel picks, with a secret made for the
// test from which the kit mints every component's token. The `cast` command is
// found in $CAST_SERVE, else on PATH, else in the Python package of python3
// (`python3 -m cast.cli`); without one the constructor throws
// cast::NotFoundError saying what to install. The server watches its standard
// input, a pipe only this process holds, and stops when it ends: a test
// process that crashes leaves no server behind.
//
// Failed expectations throw cast::testing::AssertionError with what was seen
// (GoogleTest reports an exception that escapes a test as the test's
// failure); nothing here depends on GoogleTest. The names are those of the
// Python (cast.testing) and Java (cast-testing) kits, in C++ casing:
// docs/cpp.md, "Testing your components".
#pragma once

#include <google/protobuf/message.h>

#include <chrono>
#include <condition_variable>
#include <exception>
#include <functional>
#include <initializer_list>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <stdexcept>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "cast/args.h"
#include "cast/component.h"
#include "cast/connect.h"
#include "cast/filters.h"
#include "cast/types.h"

namespace cast::testing {

// How long the kit waits when a test does not say (as in Python and Java). A
// guard against a hang, not a measurement.
inline constexpr std::chrono::milliseconds kDefaultTimeout{10000};

// A failed expectation of the kit: the message says what was expected and
// what was seen.
class AssertionError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// Asks `condition` every 10 ms until it returns true, and once more when the
// time is up; then throws AssertionError naming `what` and the timeout, with
// `seen()` if given. A condition may also throw AssertionError, meaning "not
// yet": its last message is what a timeout reports.
void waitFor(const std::function<bool()>& condition, std::chrono::milliseconds timeout = kDefaultTimeout,
             const std::string& what = "the condition", const std::function<std::string()>& seen = nullptr);

// A value as its type and its fields on one line: "google.protobuf.Int64Value {value: 3}".
std::string describeValue(const google::protobuf::Message& value);

// One line for a change: "ADD vision/count by counter (revision 3): google.protobuf.Int64Value".
std::string describeChange(const WorkingMemoryChange& change);

// How LocalSystem starts its server.
struct SystemOptions {
  // A system of these SAs, whose task managers adopt every task (default:
  // vision and language) ...
  std::vector<std::string> subarchitectures;
  // ... or a configuration's YAML file (its SAs, policies, limits, in-process components).
  std::string config;
  // Values of the configuration's variables (`cast serve --set NAME=VALUE`).
  std::map<std::string, std::string> sets;
  // How long `cast serve` may take to say it listens.
  std::chrono::milliseconds startTimeout{90000};
};

// The test acting as a component (LocalSystem::actAs): every call of a
// component with that component's identity and rights, and tasks, whose
// decisions it keeps.
class Actor : public ManagedComponent {
 public:
  // The decisions about its tasks so far (adopted or rejected), in order.
  std::vector<Task> decisions() const;
  // The task as its task manager decided it; AssertionError after `timeout`.
  Task waitForDecision(const Task& task, std::chrono::milliseconds timeout = kDefaultTimeout);

  void taskAdopted(const Task& task) override;
  void taskRejected(const Task& task) override;

 private:
  mutable std::mutex mu_;
  std::vector<Task> decided_;
};

// The changes a watch of its own delivered, in the order they came
// (LocalSystem::collectChanges, which registers the watch before it returns).
class ChangeCollector {
 public:
  ~ChangeCollector();
  ChangeCollector(const ChangeCollector&) = delete;
  ChangeCollector& operator=(const ChangeCollector&) = delete;

  // The changes collected so far (a copy), and how many.
  std::vector<WorkingMemoryChange> changes() const;
  std::size_t size() const;
  // One line per change collected.
  std::string describe() const;
  // Waits until at least `count` changes came; the first `count`. The
  // failure lists those that came.
  std::vector<WorkingMemoryChange> waitForCount(std::size_t count, std::chrono::milliseconds timeout = kDefaultTimeout);
  // Waits for a change that satisfies `test`; the first one.
  WorkingMemoryChange waitForChange(const std::function<bool(const WorkingMemoryChange&)>& test,
                                    std::chrono::milliseconds timeout = kDefaultTimeout,
                                    const std::string& what = "a matching change");
  // Forgets what was collected (collecting goes on).
  void clear();
  // Stops collecting (what was collected stays).
  void close();

 private:
  friend class LocalSystem;
  ChangeCollector() = default;
  void collect(const WorkingMemoryChange& change);
  mutable std::mutex mu_;
  std::vector<WorkingMemoryChange> changes_;
  std::unique_ptr<Connection> watcher_;
};

// A component under test running its lifecycle on a thread of its own, as
// CAST_COMPONENT_MAIN runs it: configure(args), start(), run(); stop() once at
// the end. LocalSystem::run hands it over once start() returned.
class RunningComponentBase {
 public:
  virtual ~RunningComponentBase();
  RunningComponentBase(const RunningComponentBase&) = delete;
  RunningComponentBase& operator=(const RunningComponentBase&) = delete;

  const std::string& componentId() const { return componentId_; }
  // Whether its lifecycle is still going.
  bool running() const;
  // 0 after a clean stop, 1 when a hook threw; nullopt while it runs.
  std::optional<int> exitCode() const;
  // Waits until the component stops by itself (requestStop(), a hook that
  // threw); its exit code. AssertionError after `timeout`.
  int join(std::chrono::milliseconds timeout = kDefaultTimeout);
  // Asks the component to stop and waits for its end; its exit code (assert
  // it, so that a component that failed quietly fails the test). As under
  // CAST_COMPONENT_MAIN, a run() that does not return within 10 s of the
  // request ends the process.
  int stop(std::chrono::milliseconds timeout = kDefaultTimeout);

 protected:
  RunningComponentBase(Component& component, std::string componentId);
  // Joins the lifecycle's thread (stopping the component first); derived
  // classes call it before their component goes away.
  void finish();

 private:
  friend class LocalSystem;
  void begin(std::shared_ptr<::cast::detail::Transport> transport, Args args);
  void waitStarted(std::chrono::milliseconds timeout);
  Component& component_;
  std::string componentId_;
  std::thread thread_;
  mutable std::mutex mu_;
  std::condition_variable cv_;
  bool started_ = false;
  bool ended_ = false;
  std::optional<int> exitCode_;
  std::exception_ptr error_;
};

template <class T>
class RunningComponent final : public RunningComponentBase {
 public:
  ~RunningComponent() override { finish(); }
  // The component object (its members are the test's to read).
  T& component() { return *component_; }

 private:
  friend class LocalSystem;
  RunningComponent(std::unique_ptr<T> component, std::string componentId)
      : RunningComponentBase(*component, std::move(componentId)), component_(std::move(component)) {}
  std::unique_ptr<T> component_;
};

namespace detail {
class ServeProcess;
}

// A system a test runs against: `cast serve` on a free port of 127.0.0.1, in
// a temporary directory of its own. Destroying it (or close()) stops every
// component it started and the server, and removes the directory.
class LocalSystem {
 public:
  // A system of these SAs (task managers: always).
  LocalSystem(std::initializer_list<std::string> subarchitectures);
  explicit LocalSystem(SystemOptions options = {});
  ~LocalSystem();
  LocalSystem(const LocalSystem&) = delete;
  LocalSystem& operator=(const LocalSystem&) = delete;

  // The directory's host:port, the system's name and its SAs (as the server
  // describes them), and the system's temporary directory.
  const std::string& endpoint() const;
  const std::string& name() const { return name_; }
  const std::vector<std::string>& subarchitectures() const { return subarchitectures_; }
  const std::string& directory() const { return directory_; }

  // A token for a component of this system (what `cast token` would issue).
  std::string token(const std::string& componentId, const std::string& subarchitecture,
                    bool privileged = false) const;
  // The launch contract of a component process the test starts: CAST_ENDPOINT,
  // CAST_COMPONENT_ID, CAST_SUBARCHITECTURE, CAST_TOKEN and CAST_ARGS.
  std::map<std::string, std::string> launchEnvironment(const std::string& componentId,
                                                       const std::string& subarchitecture, const Args& args = {},
                                                       bool privileged = false) const;

  // The test acting as component `componentId` of `subarchitecture`.
  Actor& actAs(const std::string& componentId, const std::string& subarchitecture, bool privileged = false);

  // A component of class T bound to the system, its hooks left to the test to
  // call (stepping). Owned by the system, closed with it.
  template <class T>
  T& bind(const std::string& componentId, const std::string& subarchitecture, bool privileged = false) {
    auto owned = std::make_unique<T>();
    T& component = *owned;
    component.bind(transport(componentId, subarchitecture, privileged));
    components_.push_back(std::move(owned));
    return component;
  }

  // A component of class T running its lifecycle (configure(args), start(),
  // run()) on a thread; returns once start() returned, so its watches are
  // registered. Owned by the system, stopped with it.
  template <class T>
  RunningComponent<T>& run(const std::string& componentId, const std::string& subarchitecture,
                           const Args& args = {}, bool privileged = false,
                           std::chrono::milliseconds timeout = kDefaultTimeout) {
    std::unique_ptr<RunningComponent<T>> running(new RunningComponent<T>(std::make_unique<T>(), componentId));
    RunningComponent<T>& handle = *running;
    running_.push_back(std::move(running));
    handle.begin(transport(componentId, subarchitecture, privileged), args);
    handle.waitStarted(timeout);
    return handle;
  }

  // Collects every change matching `filters` (default: every change of every
  // SA, with its entry); local filters mean `subarchitecture` (default: the
  // first SA). The watch is registered before this returns.
  ChangeCollector& collectChanges(const std::vector<ChangeFilter>& filters = {},
                                  const std::string& subarchitecture = "");

  // The entry, which must exist, be a T and hold `expected` (or pass `test`);
  // AssertionError saying what it holds otherwise.
  template <class T>
  Entry<T> assertEntry(const std::string& subarchitecture, const std::string& id, const T& expected) {
    Entry<T> entry = readEntry<T>(subarchitecture, id);
    if (!sameValue(entry.value, expected)) {
      throw AssertionError(where(subarchitecture, id) + " holds " + describeEntry(entry.value, entry.version,
                                                                                   entry.author) +
                           ", expected " + describeValue(expected));
    }
    return entry;
  }
  template <class T>
  Entry<T> assertEntry(const std::string& subarchitecture, const std::string& id,
                       const std::function<bool(const T&)>& test = nullptr) {
    Entry<T> entry = readEntry<T>(subarchitecture, id);
    if (test && !test(entry.value)) {
      throw AssertionError(where(subarchitecture, id) + " holds " +
                           describeEntry(entry.value, entry.version, entry.author) + ", which the test refused");
    }
    return entry;
  }
  // Waits until assertEntry holds; the entry. The failure says what the entry last held.
  template <class T>
  Entry<T> waitForEntry(const std::string& subarchitecture, const std::string& id, const T& expected,
                        std::chrono::milliseconds timeout = kDefaultTimeout) {
    std::optional<Entry<T>> found;
    waitFor([&] { return (found = assertEntry<T>(subarchitecture, id, expected)).has_value(); }, timeout,
            where(subarchitecture, id));
    return *found;
  }
  template <class T>
  Entry<T> waitForEntry(const std::string& subarchitecture, const std::string& id,
                        const std::function<bool(const T&)>& test, std::chrono::milliseconds timeout = kDefaultTimeout) {
    std::optional<Entry<T>> found;
    waitFor([&] { return (found = assertEntry<T>(subarchitecture, id, test)).has_value(); }, timeout,
            where(subarchitecture, id));
    return *found;
  }

  // What the server printed so far (for failure messages; after close(), all it printed).
  std::string output() const;
  // SIGKILL: the server is gone at once, as after a crash; clients see their
  // connections break.
  void kill();
  // A new server with empty memories on the same address (the old one is
  // killed first). Components reconnect by themselves.
  void restart();
  // Stops everything (running components' stop() once each, bound ones, the
  // server) and removes the directory; the server's exit status. Idempotent;
  // the destructor calls it.
  int close();

 private:
  std::shared_ptr<::cast::detail::Transport> transport(const std::string& componentId, const std::string& subarchitecture,
                                               bool privileged);
  Actor& observer();
  std::string listEntries(const std::string& subarchitecture) const;
  static std::string where(const std::string& subarchitecture, const std::string& id);
  static std::string describeEntry(const google::protobuf::Message& value, std::uint64_t version,
                                   const std::string& author);
  static bool sameValue(const google::protobuf::Message& a, const google::protobuf::Message& b);
  template <class T>
  Entry<T> readEntry(const std::string& subarchitecture, const std::string& id) {
    try {
      return observer().template getEntry<T>(id, subarchitecture);
    } catch (const NotFoundError&) {
      throw AssertionError("no " + where(subarchitecture, id) + "; " + listEntries(subarchitecture));
    } catch (const InvalidArgumentError& e) {
      throw AssertionError(where(subarchitecture, id) + ": " + e.message());
    }
  }

  std::string directory_;
  std::string secret_;
  std::string name_;
  std::vector<std::string> subarchitectures_;
  std::unique_ptr<detail::ServeProcess> server_;
  std::vector<std::unique_ptr<RunningComponentBase>> running_;
  std::vector<std::unique_ptr<ChangeCollector>> collectors_;
  std::vector<std::unique_ptr<Component>> components_;
  Actor* observer_ = nullptr;
  bool closed_ = false;
  int exitCode_ = 0;
  std::string output_;  // what the server printed, kept when close() removes its log
};

}  // namespace cast::testing
