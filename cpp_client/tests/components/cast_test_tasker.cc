// cast_test_tasker: a managed component that proposes tasks and works on
// them only when its SA's task manager adopts them, as a real managed
// component would. Each decision is printed as one JSON line on stdout, so a
// test can check the policy's decisions as the component saw them.
//
// args: {"tasks": N, "work_ms": M, "prefix": "t", "priorities": [..], "hold": ID}
// Proposes N tasks named <prefix>0 .. <prefix>N-1 in start(); each adopted
// task "works" for work_ms on its own thread, then completes SUCCEEDED.
// With "hold", it first adds a Counter entry ID (unless it exists) and keeps an
// ODR lock on it while it lives: the session tests kill it and check that
// the server releases the lock.
#include <iostream>
#include <mutex>
#include <thread>
#include <vector>

#include "cast/cast.h"
#include "cast_testing.pb.h"
#include "probe_json.h"

namespace {

class Tasker : public cast::ManagedComponent {
 public:
  void configure(const cast::Args& args) override {
    tasks_ = args.getInt("tasks", 3);
    workMs_ = args.getInt("work_ms", 100);
    prefix_ = args.getString("prefix", "t");
    hold_ = args.getString("hold");
    if (args.has("priorities")) {
      for (const auto& v : args.values().fields().at("priorities").list_value().values()) {
        priorities_.push_back(static_cast<std::int32_t>(v.number_value()));
      }
    }
  }

  void start() override {
    if (!hold_.empty()) {
      cast::testing::Counter c;
      c.set_writer(componentId());
      try {
        add(hold_, c);
      } catch (const cast::AlreadyExistsError&) {  // a restart: the entry outlived us
      }
      held_ = lock(hold_, cast::LockMode::ODR, "", std::chrono::seconds(30));
      print(cast::probe::Object().str("holding", hold_).unum("depth", held_.depth()));
    }
    for (std::int64_t i = 0; i < tasks_; ++i) {
      const auto priority = i < static_cast<std::int64_t>(priorities_.size()) ? priorities_[static_cast<size_t>(i)] : 0;
      cast::Task t = proposeTask(prefix_ + std::to_string(i), priority);
      print(cast::probe::Object().str("proposed", t.name()).str("task_id", t.taskId()).num("priority", priority));
    }
  }

  void taskAdopted(const cast::Task& task) override {
    print(cast::probe::Object().str("adopted", task.name()).str("task_id", task.taskId()));
    std::lock_guard<std::mutex> lock(mu_);
    // Work off the dispatcher, so several adopted tasks really run at once
    // and other callbacks are not held up.
    workers_.emplace_back([this, task] {
      if (waitForStop(std::chrono::milliseconds(workMs_))) return;  // stopped: leave it to the session end
      try {
        taskComplete(task, cast::TaskOutcome::Succeeded, "done by C++");
        print(cast::probe::Object().str("completed", task.name()).str("task_id", task.taskId()));
      } catch (const cast::CastError& e) {
        print(cast::probe::Object().str("complete_failed", task.name()).str("error", e.name()));
      }
    });
  }

  void taskRejected(const cast::Task& task) override {
    print(cast::probe::Object().str("rejected", task.name()).str("task_id", task.taskId()).str("reason", task.reason()));
  }

  void stop() override {
    if (held_.held()) held_.unlock();
    std::vector<std::thread> workers;
    {
      std::lock_guard<std::mutex> lock(mu_);
      workers.swap(workers_);
    }
    for (auto& w : workers) w.join();
  }

 private:
  void print(const cast::probe::Object& o) {
    std::lock_guard<std::mutex> lock(outMu_);
    std::cout << o.json() << std::endl;
  }

  std::int64_t tasks_ = 3;
  std::int64_t workMs_ = 100;
  std::string prefix_;
  std::string hold_;
  cast::LockGuard held_;
  std::vector<std::int32_t> priorities_;
  std::mutex mu_;
  std::mutex outMu_;
  std::vector<std::thread> workers_;
};

}  // namespace

CAST_COMPONENT_MAIN(Tasker)
