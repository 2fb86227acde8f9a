// cast_probe: a C++ component driven line by line from stdin, so the pytest
// interop tests (tests/interop/test_cpp_*.py) can interleave its calls with a
// Python component's, step by step. It is a real component started through
// the launch contract by CAST_COMPONENT_MAIN; every command goes through the
// public C++ API.
//
// Protocol: one command per line on stdin, one JSON object per line on
// stdout: {"ok": true, ...} or {"ok": false, "error": "LockedError",
// "code": "FAILED_PRECONDITION", "message": "..."}. After start() it prints
// {"ok": true, "ready": ...}. Logs go to stderr. EOF on stdin or `quit`
// stops the component. Commands ("-" means: not given / own SA):
//
//   ping | newid | whoami
//   add TYPE ID SA JSON            overwrite TYPE ID SA EXPECTED JSON
//   delete ID SA EXPECTED          get TYPE ID SA
//   getall TYPE SA LIMIT           exists ID SA
//   lock ID MODE SA TIMEOUT_MS     trylock ID MODE SA
//   unlock ID SA                   release ID SA   (drops a guard: RAII unlock)
//   copy TYPE FROM TO SA           (read, drop unknown fields, add: fidelity)
//   watch NAME JSON                cancel NAME       open_gate
//     (JSON: {"filters": [...], "gated": bool}; a gated callback blocks
//     until open_gate; CAST_PROBE_MAX_PENDING bounds the dispatcher queue;
//     "delivery": "queue|latest", "priority": "high|medium|low", "slow_ms": N:
//     options and a callback that sleeps N ms, probe_streamed.cc; each event
//     has a "seq" number: the order callbacks ran in, across watches)
//   events NAME COUNT TIMEOUT_MS   (waits for COUNT events, returns them all)
//   propose NAME PRIORITY [TYPE JSON]
//   decisions COUNT TIMEOUT_MS     complete TASK_ID OUTCOME REASON
//   retract TASK_ID                report NAME VALUE   quit
//   stress THREADS PER_THREAD      (the API from many threads at once)
//   addasync PREFIX N              overwriteasync ID N   (pipelined writes)
//   bigwrite ID SA SIZE            bigread ID SA   (a large BytesValue)
#include <google/protobuf/struct.pb.h>
#include <google/protobuf/util/json_util.h>
#include <poll.h>
#include <unistd.h>

#include <condition_variable>
#include <cstdlib>
#include <iostream>
#include <map>
#include <mutex>
#include <sstream>
#include <thread>

#include "cast/cast.h"
#include "cast_fidelity.pb.h"
#include "cast_testing.pb.h"
#include "probe_json.h"
#include "probe_stress.h"
#include "probe_streamed.h"

namespace {

using cast::probe::Object;
using cast::probe::quote;

template <class T>
struct Tag {
  using type = T;
};

// Calls fn(Tag<T>{}) for the entry type named `name` (short or full name).
template <class Fn>
auto withType(const std::string& name, Fn&& fn) {
  if (name == "Counter" || name == "cast.testing.Counter") return fn(Tag<cast::testing::Counter>{});
  if (name == "Pose" || name == "cast.testing.Pose") return fn(Tag<cast::testing::Pose>{});
  if (name == "RichEntry" || name == "cast.testing.RichEntry") return fn(Tag<cast::testing::RichEntry>{});
  throw cast::InvalidArgumentError("probe: unknown type '" + name + "' (Counter, Pose, RichEntry)");
}

template <class T>
T parseJson(const std::string& json) {
  T value;
  auto status = google::protobuf::util::JsonStringToMessage(json, &value);
  if (!status.ok()) throw cast::InvalidArgumentError("probe: bad JSON for " + cast::typeName<T>() + ": " + json);
  return value;
}

std::string sa(const std::string& token) { return token == "-" ? "" : token; }

std::optional<std::uint64_t> expected(const std::string& token) {
  if (token == "-" || token.empty()) return std::nullopt;
  return std::stoull(token);
}

cast::LockMode lockMode(const std::string& token) {
  if (token == "O") return cast::LockMode::O;
  if (token == "OD") return cast::LockMode::OD;
  if (token == "ODR") return cast::LockMode::ODR;
  throw cast::InvalidArgumentError("probe: lock mode must be O, OD or ODR, not " + token);
}

cast::Operation operation(const std::string& name) {
  if (name == "ADD") return cast::Operation::Add;
  if (name == "OVERWRITE") return cast::Operation::Overwrite;
  if (name == "DELETE") return cast::Operation::Delete;
  throw cast::InvalidArgumentError("probe: operation must be ADD, OVERWRITE or DELETE, not " + name);
}

cast::TaskOutcome outcome(const std::string& name) {
  if (name == "SUCCEEDED") return cast::TaskOutcome::Succeeded;
  if (name == "FAILED") return cast::TaskOutcome::Failed;
  if (name == "ABANDONED") return cast::TaskOutcome::Abandoned;
  throw cast::InvalidArgumentError("probe: outcome must be SUCCEEDED, FAILED or ABANDONED, not " + name);
}

// Splits the first `n` whitespace-separated tokens; the rest of the line
// (a JSON value, a reason) is the last element.
std::vector<std::string> split(const std::string& line, size_t n) {
  std::vector<std::string> out;
  size_t pos = 0;
  for (size_t i = 0; i < n; ++i) {
    pos = line.find_first_not_of(' ', pos);
    if (pos == std::string::npos) break;
    size_t end = line.find(' ', pos);
    out.push_back(line.substr(pos, end == std::string::npos ? std::string::npos : end - pos));
    pos = end == std::string::npos ? line.size() : end;
  }
  pos = line.find_first_not_of(' ', pos);
  out.push_back(pos == std::string::npos ? "" : line.substr(pos));
  return out;
}

std::string taskJson(const cast::Task& t) {
  return Object()
      .str("task_id", t.taskId())
      .str("name", t.name())
      .str("state", cast::toString(t.state()))
      .str("subarchitecture", t.subarchitecture())
      .str("component", t.component())
      .num("priority", t.priority())
      .str("reason", t.reason())
      .json();
}

class Probe : public cast::ManagedComponent {
 public:
  Probe() {
    // A small dispatcher queue, for the tests of a stuck watcher.
    if (const char* max = std::getenv("CAST_PROBE_MAX_PENDING")) setMaxPendingCallbacks(std::stoul(max));
  }

  ~Probe() override {
    // Locks still held at exit are left to the server, which releases them
    // when the session ends (that is what the session tests check).
    for (auto& kv : guards_) {
      for (auto& g : kv.second) g.release();
    }
  }

  void start() override { emit(Object().boolean("ok", true).boolean("ready", true).str("id", componentId()).json()); }

  void run() override {
    std::string buffer;
    char chunk[4096];
    while (running()) {
      // poll, not a blocking read: stop() must be able to end run() at once.
      pollfd pfd{0, POLLIN, 0};
      int ready = ::poll(&pfd, 1, 100);
      if (ready <= 0) continue;
      ssize_t n = ::read(0, chunk, sizeof chunk);
      if (n <= 0) break;  // EOF: the test is done with us
      buffer.append(chunk, static_cast<size_t>(n));
      size_t nl;
      while ((nl = buffer.find('\n')) != std::string::npos) {
        std::string line = buffer.substr(0, nl);
        buffer.erase(0, nl + 1);
        if (!line.empty()) emit(handle(line));
        if (!running()) return;
      }
    }
    requestStop();
  }

  void taskAdopted(const cast::Task& task) override { record(task); }
  void taskRejected(const cast::Task& task) override { record(task); }

 private:
  struct Watch {
    cast::WatchHandle handle;
    std::vector<std::string> events;
    bool allOnDispatcher = true;
  };

  void emit(const std::string& json) {
    std::lock_guard<std::mutex> lock(outMu_);
    std::cout << json << std::endl;
  }

  void record(const cast::Task& task) {
    std::string data;
    if (task.hasData()) data = cast::probe::messageJson(*task.data<cast::testing::Counter>());
    std::string json = taskJson(task);
    json.pop_back();  // reopen the object to add what only a hook knows
    json += ", \"on_dispatcher\": " + std::string(onDispatcherThread() ? "true" : "false");
    if (!data.empty()) json += ", \"data\": " + data;
    json += "}";
    std::lock_guard<std::mutex> lock(mu_);
    decisions_.push_back(json);
    cv_.notify_all();
  }

  std::string handle(const std::string& line) {
    try {
      return Object().boolean("ok", true).raw("result", dispatch(line)).json();
    } catch (const cast::CastError& e) {
      return Object().boolean("ok", false).str("error", e.name()).str("code", e.code()).str("message", e.message()).json();
    } catch (const std::exception& e) {
      return Object().boolean("ok", false).str("error", "std::exception").str("code", "").str("message", e.what()).json();
    }
  }

  std::string dispatch(const std::string& line) {
    const std::string cmd = split(line, 1)[0];
    if (cmd == "ping") return "{}";
    if (cmd == "quit") {
      requestStop();
      return "{}";
    }
    if (cmd == "whoami") {
      return Object().str("id", componentId()).str("sa", subarchitecture()).boolean("privileged", privileged()).json();
    }
    if (cmd == "newid") return Object().str("id", newId()).json();
    if (cmd == "add") {  // add TYPE ID SA JSON
      auto a = split(line, 4);
      return withType(a[1], [&](auto tag) {
        using T = typename decltype(tag)::type;
        auto r = add(a[2], parseJson<T>(a[4]), sa(a[3]));
        return Object().unum("revision", r.revision).unum("version", r.version).json();
      });
    }
    if (cmd == "overwrite") {  // overwrite TYPE ID SA EXPECTED JSON
      auto a = split(line, 5);
      return withType(a[1], [&](auto tag) {
        using T = typename decltype(tag)::type;
        auto r = overwrite(a[2], parseJson<T>(a[5]), sa(a[3]), expected(a[4]));
        return Object().unum("revision", r.revision).unum("version", r.version).json();
      });
    }
    if (cmd == "delete") {  // delete ID SA EXPECTED
      auto a = split(line, 4);
      auto r = deleteEntry(a[1], sa(a[2]), expected(a[3]));
      return Object().unum("revision", r.revision).unum("version", r.version).json();
    }
    if (cmd == "get") {  // get TYPE ID SA
      auto a = split(line, 4);
      return withType(a[1], [&](auto tag) {
        using T = typename decltype(tag)::type;
        auto e = getEntry<T>(a[2], sa(a[3]));
        return Object()
            .message("value", e.value)
            .str("type", e.type)
            .unum("version", e.version)
            .str("author", e.author)
            .unum("revision", e.revision)
            .json();
      });
    }
    if (cmd == "getall") {  // getall TYPE SA LIMIT
      auto a = split(line, 4);
      return withType(a[1], [&](auto tag) {
        using T = typename decltype(tag)::type;
        std::vector<std::string> items;
        for (const auto& e : getAll<T>(sa(a[2]), static_cast<std::uint32_t>(std::stoul(a[3])))) {
          items.push_back(Object().str("id", e.id()).unum("version", e.version).message("value", e.value).json());
        }
        return Object().raw("entries", cast::probe::array(items)).json();
      });
    }
    if (cmd == "exists") {  // exists ID SA
      auto a = split(line, 3);
      return Object().boolean("exists", exists(a[1], sa(a[2]))).json();
    }
    if (cmd == "lock") {  // lock ID MODE SA TIMEOUT_MS
      auto a = split(line, 5);
      std::optional<std::chrono::milliseconds> timeout;
      if (a[4] != "-") timeout = std::chrono::milliseconds(std::stol(a[4]));
      cast::LockGuard guard = lock(a[1], lockMode(a[2]), sa(a[3]), timeout);
      const std::uint32_t depth = guard.depth();
      std::lock_guard<std::mutex> l(mu_);
      guards_[guard.address().subarchitecture + "/" + a[1]].push_back(std::move(guard));
      return Object().unum("depth", depth).json();
    }
    if (cmd == "trylock") {  // trylock ID MODE SA
      auto a = split(line, 4);
      return Object().boolean("locked", tryLock(a[1], lockMode(a[2]), sa(a[3]))).json();
    }
    if (cmd == "unlock") {  // unlock ID SA
      auto a = split(line, 3);
      return Object().unum("depth", unlock(a[1], sa(a[2]))).json();
    }
    if (cmd == "release") {  // release ID SA: the guard's destructor unlocks
      auto a = split(line, 3);
      const std::string key = (sa(a[2]).empty() ? subarchitecture() : a[2]) + "/" + a[1];
      std::vector<cast::LockGuard> dropped;
      {
        std::lock_guard<std::mutex> l(mu_);
        auto it = guards_.find(key);
        if (it == guards_.end() || it->second.empty()) throw cast::InvalidArgumentError("probe: no guard for " + key);
        dropped.push_back(std::move(it->second.back()));
        it->second.pop_back();
      }
      dropped.clear();  // unlocks here, outside the probe's mutex
      return "{}";
    }
    if (cmd == "copy") {  // copy TYPE FROM TO SA
      auto a = split(line, 5);
      return withType(a[1], [&](auto tag) {
        using T = typename decltype(tag)::type;
        T value = get<T>(a[2], sa(a[4]));
        // Only fields C++ understood survive: proves the parse, not a
        // pass-through of unknown bytes.
        value.DiscardUnknownFields();
        auto r = add(a[3], value, sa(a[4]));
        return Object().unum("revision", r.revision).json();
      });
    }
    if (cmd == "watch") return watchCommand(split(line, 2));  // watch NAME JSON
    if (cmd == "stress") {  // stress THREADS PER_THREAD (probe_stress.cc)
      auto a = split(line, 3);
      return cast::probe::stress(*this, std::stoi(a[1]), std::stoi(a[2]));
    }
    if (cmd == "addasync" || cmd == "overwriteasync") {  // addasync PREFIX N | overwriteasync ID N
      auto a = split(line, 3);
      return cmd == "addasync" ? cast::probe::addAsync(*this, a[1], std::stoi(a[2]))
                               : cast::probe::overwriteAsync(*this, a[1], std::stoi(a[2]));
    }
    if (cmd == "bigwrite") {  // bigwrite ID SA SIZE
      auto a = split(line, 4);
      return cast::probe::bigWrite(*this, a[1], sa(a[2]), std::stoul(a[3]));
    }
    if (cmd == "bigread") {  // bigread ID SA
      auto a = split(line, 3);
      return cast::probe::bigRead(*this, a[1], sa(a[2]));
    }
    if (cmd == "open_gate") {  // lets gated watch callbacks return
      {
        std::lock_guard<std::mutex> l(mu_);
        gateOpen_ = true;
      }
      cv_.notify_all();
      return "{}";
    }
    if (cmd == "cancel") {  // cancel NAME
      auto a = split(line, 2);
      std::lock_guard<std::mutex> l(mu_);
      auto it = watches_.find(a[1]);
      if (it == watches_.end()) throw cast::InvalidArgumentError("probe: no watch " + a[1]);
      it->second->handle.cancel();
      return Object().boolean("active", it->second->handle.active()).json();
    }
    if (cmd == "events") {  // events NAME COUNT TIMEOUT_MS
      auto a = split(line, 4);
      std::unique_lock<std::mutex> l(mu_);
      auto it = watches_.find(a[1]);
      if (it == watches_.end()) throw cast::InvalidArgumentError("probe: no watch " + a[1]);
      auto w = it->second;
      const size_t count = std::stoul(a[2]);
      cv_.wait_for(l, std::chrono::milliseconds(std::stol(a[3])), [&] { return w->events.size() >= count; });
      auto err = w->handle.error();
      return Object()
          .raw("events", cast::probe::array(w->events))
          .boolean("on_dispatcher", w->allOnDispatcher)
          .str("error", err ? err->name() : "")
          .json();
    }
    if (cmd == "propose") {  // propose NAME PRIORITY [TYPE JSON]
      auto a = split(line, 4);
      const auto priority = static_cast<std::int32_t>(std::stol(a[2]));
      cast::Task task = a[3].empty() ? proposeTask(a[1], priority) : withType(a[3], [&](auto tag) {
        using T = typename decltype(tag)::type;
        return proposeTask(a[1], parseJson<T>(a[4]), priority);
      });
      return taskJson(task);
    }
    if (cmd == "decisions") {  // decisions COUNT TIMEOUT_MS
      auto a = split(line, 3);
      std::unique_lock<std::mutex> l(mu_);
      const size_t count = std::stoul(a[1]);
      cv_.wait_for(l, std::chrono::milliseconds(std::stol(a[2])), [&] { return decisions_.size() >= count; });
      return Object().raw("decisions", cast::probe::array(decisions_)).json();
    }
    if (cmd == "complete") {  // complete TASK_ID OUTCOME REASON
      auto a = split(line, 3);
      taskComplete(a[1], outcome(a[2]), a[3]);
      return "{}";
    }
    if (cmd == "retract") {  // retract TASK_ID
      retractTask(split(line, 2)[1]);
      return "{}";
    }
    if (cmd == "report") {  // report NAME VALUE (std::stod reads "nan" and "inf" too: the server judges)
      auto a = split(line, 3);
      report(a[1], std::stod(a[2]));
      return "{}";
    }
    throw cast::InvalidArgumentError("probe: unknown command '" + cmd + "'");
  }

  // watch NAME {"filters": [{"kind": "global|local|address|source|operation", ...}]}
  std::string watchCommand(const std::vector<std::string>& a) {
    const std::string& name = a[1];
    auto spec = parseJson<google::protobuf::Struct>(a[2]);
    if (!spec.fields().count("filters")) throw cast::InvalidArgumentError("probe: watch needs {\"filters\": [...]}");
    std::vector<cast::ChangeFilter> filters;
    for (const auto& item : spec.fields().at("filters").list_value().values()) {
      const auto& f = item.struct_value().fields();
      auto text = [&](const char* key) {
        auto it = f.find(key);
        return it == f.end() ? std::string() : it->second.string_value();
      };
      cast::Operations ops;
      if (auto it = f.find("ops"); it != f.end()) {
        for (const auto& op : it->second.list_value().values()) ops.push_back(operation(op.string_value()));
      }
      const bool entry = f.count("include_entry") && f.at("include_entry").bool_value();
      const std::string kind = text("kind");
      if (kind == "global") filters.push_back(cast::globalTypeFilter(text("type"), ops, entry));
      else if (kind == "local") filters.push_back(cast::localTypeFilter(text("type"), ops, entry));
      else if (kind == "address") filters.push_back(cast::addressFilter(text("id"), ops, text("sa"), entry));
      else if (kind == "source") filters.push_back(cast::sourceFilter(text("component"), ops, text("sa"), entry));
      else if (kind == "operation") filters.push_back(cast::operationFilter(ops, text("sa") == "local", entry));
      else throw cast::InvalidArgumentError("probe: unknown filter kind '" + kind + "'");
    }
    auto w = std::make_shared<Watch>();
    // A gated watch's callback blocks until open_gate: a stuck component.
    const bool gated = spec.fields().count("gated") && spec.fields().at("gated").bool_value();
    const auto slow = cast::probe::slowCallback(spec);
    auto callback = [this, w, gated, slow](const cast::WorkingMemoryChange& c) {
      if (gated) {
        std::unique_lock<std::mutex> l(mu_);
        cv_.wait(l, [this] { return gateOpen_; });
      }
      if (slow.count()) std::this_thread::sleep_for(slow);  // a consumer slower than the writer
      Object o;
      o.unum("revision", c.revision())
          .str("operation", cast::toString(c.operation()))
          .str("sa", c.subarchitecture())
          .str("id", c.id())
          .str("type", c.type())
          .unum("version", c.version())
          .str("source", c.sourceComponent())
          .str("source_sa", c.sourceSubarchitecture());
      if (c.hasEntry() && c.type() == "cast.testing.Counter") o.message("value", c.entry<cast::testing::Counter>().value);
      cast::probe::describeStreamed(o, c);
      std::lock_guard<std::mutex> l(mu_);
      o.unum("seq", ++delivered_);  // the order callbacks ran in, across watches (priorities)
      w->events.push_back(o.json());
      w->allOnDispatcher = w->allOnDispatcher && onDispatcherThread();
      cv_.notify_all();
    };
    w->handle = onChange(filters, callback, cast::probe::watchOptions(spec));
    std::lock_guard<std::mutex> l(mu_);
    watches_[name] = w;
    return Object().unum("watch_id", w->handle.watchId()).json();
  }

  std::mutex outMu_;
  std::mutex mu_;
  std::condition_variable cv_;
  std::map<std::string, std::vector<cast::LockGuard>> guards_;
  std::map<std::string, std::shared_ptr<Watch>> watches_;
  std::vector<std::string> decisions_;
  bool gateOpen_ = false;
  std::uint64_t delivered_ = 0;  // callbacks run so far, every watch (guarded by mu_)
};

}  // namespace

CAST_COMPONENT_MAIN(Probe)
