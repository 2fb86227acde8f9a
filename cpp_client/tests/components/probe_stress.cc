// cast_probe's `stress` command (see probe_stress.h and cast_probe.cc).
#include "probe_stress.h"

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <mutex>
#include <set>
#include <stdexcept>
#include <thread>
#include <utility>
#include <vector>

#include "cast_testing.pb.h"
#include "probe_json.h"

namespace cast::probe {

// Every thread adds, reads, overwrites (versioned), locks and unlocks its own
// entries at once, while one watch counts the changes: the API shared by
// threads, against a real server.
std::string stress(Component& component, int threads, int perThread) {
  std::mutex mu;
  std::condition_variable cv;
  std::set<std::pair<std::string, std::uint64_t>> seen;  // (id, version): each change once
  int duplicates = 0;
  auto handle =
      component.onChange(cast::localTypeFilter<cast::testing::Counter>(), [&](const cast::WorkingMemoryChange& c) {
        std::lock_guard<std::mutex> l(mu);
        if (!seen.insert({c.id(), c.version()}).second) ++duplicates;
        cv.notify_all();
      });
  std::atomic<int> errors{0};
  std::vector<std::string> firstError;
  std::vector<std::thread> workers;
  for (int t = 0; t < threads; ++t) {
    workers.emplace_back([&, t] {
      for (int i = 0; i < perThread; ++i) {
        try {
          const std::string id = component.newId();
          cast::testing::Counter c;
          c.set_writer("stress-" + std::to_string(t));
          c.set_value(i);
          const std::uint64_t added = component.add(id, c).version;
          if (component.get<cast::testing::Counter>(id).value() != i) {
            throw std::runtime_error("read back a wrong value");
          }
          c.set_value(i + 1);
          {
            cast::LockGuard guard = component.lock(id, cast::LockMode::OD);
            component.overwrite(id, c, "", added);
          }
          if (!component.tryLock(id, cast::LockMode::O)) throw std::runtime_error("could not lock an entry of its own");
          component.unlock(id);
        } catch (const std::exception& e) {
          if (errors++ == 0) {
            std::lock_guard<std::mutex> l(mu);
            firstError.push_back(e.what());
          }
        }
      }
    });
  }
  for (auto& w : workers) w.join();
  const size_t expected = static_cast<size_t>(threads) * static_cast<size_t>(perThread) * 2;  // add + overwrite
  {
    std::unique_lock<std::mutex> l(mu);
    cv.wait_for(l, std::chrono::seconds(30), [&] { return seen.size() >= expected; });
  }
  handle.cancel();
  component.drain(std::chrono::milliseconds(5000));
  std::lock_guard<std::mutex> l(mu);
  return Object()
      .num("errors", errors.load())
      .str("first_error", firstError.empty() ? "" : firstError[0])
      .unum("changes", seen.size())
      .num("duplicates", duplicates)
      .json();
}

}  // namespace cast::probe
