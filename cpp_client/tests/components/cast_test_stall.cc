// cast_test_stall: every kind of call at once against a server that stopped
// answering, for tests/interop/test_hung_server.py. One connection per call
// (cast::connect, its tokens minted from $CAST_SECRET), with the call timeout
// $CAST_STALL_CALL_TIMEOUT_MS and lock timeout $CAST_STALL_LOCK_TIMEOUT_MS.
// Commands on stdin, one JSON line per answer on stdout (the same protocol as
// tests/interop/stall_client.py and cast.itest.Stall):
//
//   (start)     {"ready": true} once every connection is open and has used its streams
//   acked N     N adds by the writer; {"acked": [ids]}
//   stall       every call at once; a line {"call", "seconds", "error", "message"} per call as it
//               ends, then {"stalled": true}
//   recover     each connection writes until it succeeds; {"recovered", "seconds", "tries"} each,
//               then {"recovered_all": true}
//   expect REV  waits (30 s) until the watcher saw revision REV; {"revisions": [every one seen]}
//   quit        closes everything and exits 0
//
//   cast_test_stall PREFIX
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <functional>
#include <iostream>
#include <map>
#include <memory>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "cast/cast.h"
#include "cast_testing.pb.h"
#include "probe_json.h"

namespace {

using cast::probe::Object;
using Clock = std::chrono::steady_clock;

std::mutex outMu;

void say(const std::string& line) {
  std::lock_guard<std::mutex> lock(outMu);
  std::cout << line << std::endl;
}

std::chrono::milliseconds envMillis(const char* name, long fallback) {
  const char* value = std::getenv(name);
  return std::chrono::milliseconds(value ? std::stol(value) : fallback);
}

cast::testing::Counter counter(std::int64_t value) {
  cast::testing::Counter c;
  c.set_writer("cpp");
  c.set_value(value);
  return c;
}

double since(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::cerr << "usage: " << argv[0] << " PREFIX" << std::endl;
    return 2;
  }
  const std::string p = argv[1];
  const auto callTimeout = envMillis("CAST_STALL_CALL_TIMEOUT_MS", 3000);
  const auto lockTimeout = envMillis("CAST_STALL_LOCK_TIMEOUT_MS", 4000);
  const std::vector<std::string> kinds = {"add",  "add_async", "overwrite", "delete", "batch",  "lock",  "try_lock",
                                          "unlock", "get", "get_all",   "exists",    "watch",  "report"};
  try {
    auto open = [&](const std::string& who) {
      cast::ConnectOptions options;
      options.componentId = p + "-" + who;
      options.subarchitecture = "vision";
      options.callTimeout = callTimeout;
      return cast::connect(options);
    };
    auto writer = open("writer");
    auto watcher = open("watcher");
    std::mutex seenMu;
    std::condition_variable seenChanged;
    std::vector<std::uint64_t> seen;
    auto watch = watcher->onChange(cast::operationFilter({}, true), [&](const cast::WorkingMemoryChange& change) {
      std::lock_guard<std::mutex> lock(seenMu);
      seen.push_back(change.revision());
      seenChanged.notify_all();
    });
    std::map<std::string, std::unique_ptr<cast::Connection>> conns;
    for (const auto& kind : kinds) conns[kind] = open(kind);
    // Every stream a call uses is open before the stall, as in a component that has been running.
    conns["add"]->add(p + "-warm-add", counter(0));
    conns["add_async"]->addAsync(p + "-warm-async", counter(0)).get();
    conns["overwrite"]->add(p + "-ow", counter(0));
    conns["delete"]->add(p + "-del", counter(0));
    conns["batch"]->add(p + "-warm-batch", counter(0));
    conns["lock"]->add(p + "-lk", counter(0));
    conns["lock"]->lock(p + "-lk", cast::LockMode::O).unlock();
    conns["try_lock"]->add(p + "-warm-try", counter(0));
    conns["unlock"]->add(p + "-ul", counter(0));
    conns["unlock"]->lock(p + "-ul", cast::LockMode::O).release();
    conns["get"]->exists(p + "-ow");
    auto warmWatch = conns["watch"]->onChange(cast::addressFilter(p + "-ow"), [](const auto&) {});  // stream open
    conns["report"]->report("warm", 1);
    say(Object().boolean("ready", true).json());

    int ackedCount = 0;
    std::string line;
    while (std::getline(std::cin, line)) {
      std::istringstream words(line);
      std::string cmd;
      words >> cmd;
      if (cmd == "acked") {
        int n = 0;
        words >> n;
        std::vector<std::string> ids;
        for (int i = 0; i < n; ++i) {
          const std::string id = p + "-acked-" + std::to_string(ackedCount++);
          writer->add(id, counter(i));
          ids.push_back(cast::probe::quote(id));
        }
        say(Object().raw("acked", cast::probe::array(ids)).json());
      } else if (cmd == "stall") {
        const auto start = Clock::now();
        std::map<std::string, std::function<void()>> calls = {
            {"add", [&] { conns["add"]->add(p + "-stalled-add", counter(1)); }},
            {"add_async", [&] { conns["add_async"]->addAsync(p + "-stalled-async", counter(1)).get(); }},
            {"overwrite", [&] { conns["overwrite"]->overwrite(p + "-ow", counter(1)); }},
            {"delete", [&] { conns["delete"]->deleteEntry(p + "-del"); }},
            {"batch",
             [&] {
               auto value = counter(2);
               conns["batch"]->batch({cast::BatchWrite::add(p + "-stalled-batch", value)});
             }},
            {"lock", [&] { conns["lock"]->lock(p + "-lk", cast::LockMode::O, "", lockTimeout).release(); }},
            {"try_lock", [&] { conns["try_lock"]->tryLock(p + "-lk", cast::LockMode::O); }},
            {"unlock", [&] { conns["unlock"]->unlock(p + "-ul"); }},
            {"get", [&] { conns["get"]->get<cast::testing::Counter>(p + "-ow"); }},
            {"get_all", [&] { conns["get_all"]->getAll<cast::testing::Counter>(); }},
            {"exists", [&] { conns["exists"]->exists(p + "-ow"); }},
            {"watch", [&] { conns["watch"]->onChange(cast::operationFilter({}, true), [](const auto&) {}); }},
            {"report", [&] { conns["report"]->report("stalled", 1); }},
        };
        std::vector<std::thread> threads;
        for (auto& [kind, fn] : calls) {
          threads.emplace_back([&, kind = kind, fn = fn] {
            Object out;
            out.str("call", kind);
            try {
              fn();
              out.num("ms", static_cast<std::int64_t>(since(start) * 1000)).raw("error", "null");
            } catch (const cast::CastError& e) {
              out.num("ms", static_cast<std::int64_t>(since(start) * 1000)).str("error", e.name()).str("message", e.message());
            }
            say(out.json());
          });
        }
        for (auto& t : threads) t.join();
        say(Object().boolean("stalled", true).json());
      } else if (cmd == "recover") {
        std::vector<std::thread> threads;
        for (const auto& kind : kinds) {
          threads.emplace_back([&, kind] {
            const auto start = Clock::now();
            int tries = 0;
            std::string last;
            while (since(start) < 60) {
              ++tries;
              try {
                conns[kind]->add(p + "-recovered-" + kind, counter(3));
                last.clear();
                break;
              } catch (const cast::AlreadyExistsError&) {
                last.clear();  // an earlier try was applied after all
                break;
              } catch (const cast::CastError& e) {
                last = std::string(e.name()) + ": " + e.message();
                std::this_thread::sleep_for(std::chrono::milliseconds(50));
              }
            }
            Object out;
            out.str("recovered", kind).num("ms", static_cast<std::int64_t>(since(start) * 1000)).num("tries", tries);
            if (!last.empty()) out.str("error", last);
            say(out.json());
          });
        }
        for (auto& t : threads) t.join();
        say(Object().boolean("recovered_all", true).json());
      } else if (cmd == "expect") {
        std::uint64_t revision = 0;
        words >> revision;
        std::unique_lock<std::mutex> lock(seenMu);
        seenChanged.wait_for(lock, std::chrono::seconds(30), [&] {
          for (auto r : seen) {
            if (r >= revision) return true;
          }
          return false;
        });
        std::vector<std::string> revisions;
        for (auto r : seen) revisions.push_back(std::to_string(r));
        say(Object().raw("revisions", cast::probe::array(revisions)).json());
      } else if (cmd == "quit") {
        break;
      }
    }
    watch.cancel();
    for (auto& [kind, conn] : conns) conn->close();
    watcher->close();
    writer->close();
    return 0;
  } catch (const cast::CastError& e) {
    say(Object().str("error", e.name()).str("message", e.message()).json());
    return 1;
  }
}
