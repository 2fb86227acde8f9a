// cast_test_barrier: the C++ twin of the start-barrier components in
// tests/orchestrator/components/barrier_components.py (BarrierWriter and
// BarrierWatcher), for tests/interop/test_start_barrier.py. argv[1] says which:
//
//   writer   privileged; args {"sa": "b", "count": N}. First thing in run():
//            adds <id>-0 .. <id>-<N-1> (Int64Value i), then <id>-end (Int64Value
//            N), to SA `sa`; then waits for stop.
//   watcher  watches ADDs to its own SA from start(); ignores seen-* entries;
//            counts each writer's entries <writer>-<i> (split at the last '-'),
//            and at <writer>-end adds seen-<id>-<writer> (Int64Value: how many
//            it saw) to its own SA.
#include <google/protobuf/wrappers.pb.h>

#include <cstring>
#include <iostream>
#include <map>
#include <mutex>
#include <string>

#include "cast/cast.h"

namespace {

using google::protobuf::Int64Value;

Int64Value int64(std::int64_t v) {
  Int64Value value;
  value.set_value(v);
  return value;
}

class BarrierWriter : public cast::UnmanagedComponent {
 public:
  void configure(const cast::Args& args) override {
    sa_ = args.getString("sa");
    count_ = args.getInt("count");
  }

  void run() override {
    for (std::int64_t i = 0; i < count_; ++i) add(componentId() + "-" + std::to_string(i), int64(i), sa_);
    add(componentId() + "-end", int64(count_), sa_);
    waitForStop();
  }

 private:
  std::string sa_;
  std::int64_t count_ = 0;
};

class BarrierWatcher : public cast::UnmanagedComponent {
 public:
  void start() override {
    onChange(cast::operationFilter({cast::Operation::Add}, true),
             [this](const cast::WorkingMemoryChange& change) { added(change); });
  }

 private:
  void added(const cast::WorkingMemoryChange& change) {
    const std::string& id = change.id();
    if (id.rfind("seen-", 0) == 0) return;  // another watcher's report
    const auto dash = id.rfind('-');
    const std::string writer = dash == std::string::npos ? std::string() : id.substr(0, dash);
    const std::string rest = dash == std::string::npos ? id : id.substr(dash + 1);
    std::int64_t seen;
    {
      std::lock_guard<std::mutex> lock(mu_);
      if (rest != "end") {
        ++seen_[writer];
        return;
      }
      seen = seen_[writer];
    }
    add("seen-" + componentId() + "-" + writer, int64(seen));
  }

  std::mutex mu_;
  std::map<std::string, std::int64_t> seen_;
};

}  // namespace

int main(int argc, char** argv) {
  const std::string role = argc > 1 ? argv[1] : "";
  if (role != "writer" && role != "watcher" && role != "-h" && role != "--help") {
    std::cerr << "usage: " << argv[0] << " writer|watcher   (args from CAST_ARGS, as cast run sets them)" << std::endl;
    return 2;
  }
  return cast::runMain(
      [&role]() -> std::unique_ptr<cast::Component> {
        if (role == "writer") return std::make_unique<BarrierWriter>();
        return std::make_unique<BarrierWatcher>();
      },
      argc, argv);
}
