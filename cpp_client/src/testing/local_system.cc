// A testing kit for components (cast/testing.h): the system, what runs in
// it, and the waits and words of failed expectations.
#include "cast/testing.h"

#include <google/protobuf/text_format.h>
#include <google/protobuf/util/message_differencer.h>
#include <grpcpp/grpcpp.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <ctime>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>

#include "cast/credentials.h"
#include "cast/grpc_transport.h"
#include "cast/runner.h"
#include "cast/v1/directory.grpc.pb.h"
#include "cast/v1/inspection.grpc.pb.h"
#include "jwt.h"
#include "serve_process.h"

namespace cast::testing {

namespace {

// The id under which the kit itself reads (assertEntry): privileged, in the first SA.
constexpr char kObserver[] = "cast-testing";
constexpr std::size_t kMaxValueChars = 300;

std::string seconds(std::chrono::milliseconds duration) {
  std::ostringstream out;
  out << static_cast<double>(duration.count()) / 1000.0;
  return out.str();
}

// A YAML (and JSON) string.
std::string quoted(const std::string& text) {
  std::string out = "\"";
  for (char c : text) {
    if (c == '"' || c == '\\') out += '\\';
    out += c;
  }
  return out + "\"";
}

std::string newDirectory() {
  const char* tmp = std::getenv("TMPDIR");
  std::string pattern = std::string(tmp != nullptr && *tmp != '\0' ? tmp : "/tmp") + "/cast-testing-XXXXXX";
  if (::mkdtemp(pattern.data()) == nullptr) {
    throw UnavailableError("cannot make a temporary directory (" + pattern + ") for the test's system");
  }
  return pattern;
}

// A fresh secret for the test (32 random bytes as base64url), in a file only
// its owner reads: what `cast serve --secret-file` takes.
std::string newSecret(const std::string& path) {
  std::random_device random;
  std::string bytes(32, '\0');
  for (auto& b : bytes) b = static_cast<char>(random() & 0xff);
  const std::string secret = cast::detail::base64UrlEncode(bytes);
  {
    std::ofstream out(path);
    out << secret << "\n";
  }
  ::chmod(path.c_str(), 0600);
  return secret;
}

std::shared_ptr<grpc::Channel> channelTo(const std::string& endpoint) {
  return grpc::CreateChannel(endpoint, grpc::InsecureChannelCredentials());
}

std::string cut(std::string text) {
  if (text.size() > kMaxValueChars) {
    text = text.substr(0, kMaxValueChars) + "... (" + std::to_string(text.size()) + " characters)";
  }
  return text;
}

}  // namespace

// ------------------------------------------------------------------ waiting and words

void waitFor(const std::function<bool()>& condition, std::chrono::milliseconds timeout, const std::string& what,
             const std::function<std::string()>& seen) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  std::string failure;
  while (true) {
    failure.clear();
    try {
      if (condition()) return;
    } catch (const AssertionError& e) {
      failure = e.what();
    }
    if (std::chrono::steady_clock::now() >= deadline) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  std::string message = "timed out after " + seconds(timeout) + " s waiting for " + what;
  if (!failure.empty()) {
    message += ": " + failure;
  } else if (seen) {
    message += "; seen: " + seen();
  }
  throw AssertionError(message);
}

std::string describeValue(const google::protobuf::Message& value) {
  std::string body;
  google::protobuf::TextFormat::Printer printer;
  printer.SetSingleLineMode(true);
  printer.PrintToString(value, &body);
  while (!body.empty() && body.back() == ' ') body.pop_back();
  return cut(value.GetDescriptor()->full_name() + " {" + body + "}");
}

std::string describeChange(const WorkingMemoryChange& change) {
  return std::string(toString(change.operation())) + " " + change.subarchitecture() + "/" + change.id() + " by " +
         change.sourceComponent() + " (revision " + std::to_string(change.revision()) + "): " + change.type();
}

// ------------------------------------------------------------------ Actor

std::vector<Task> Actor::decisions() const {
  std::lock_guard<std::mutex> lock(mu_);
  return decided_;
}

void Actor::taskAdopted(const Task& task) {
  std::lock_guard<std::mutex> lock(mu_);
  decided_.push_back(task);
}

void Actor::taskRejected(const Task& task) {
  std::lock_guard<std::mutex> lock(mu_);
  decided_.push_back(task);
}

Task Actor::waitForDecision(const Task& task, std::chrono::milliseconds timeout) {
  std::optional<Task> found;
  waitFor(
      [&] {
        for (const Task& t : decisions()) {
          if (t.taskId() == task.taskId()) {
            found = t;
            return true;
          }
        }
        return false;
      },
      timeout, "the decision about task " + task.taskId() + " of " + componentId(),
      [&] { return std::to_string(decisions().size()) + " decision(s) about other tasks"; });
  return *found;
}

// ------------------------------------------------------------------ ChangeCollector

ChangeCollector::~ChangeCollector() { close(); }

void ChangeCollector::collect(const WorkingMemoryChange& change) {
  std::lock_guard<std::mutex> lock(mu_);
  changes_.push_back(change);
}

std::vector<WorkingMemoryChange> ChangeCollector::changes() const {
  std::lock_guard<std::mutex> lock(mu_);
  return changes_;
}

std::size_t ChangeCollector::size() const {
  std::lock_guard<std::mutex> lock(mu_);
  return changes_.size();
}

std::string ChangeCollector::describe() const {
  const auto all = changes();
  if (all.empty()) return "no changes";
  std::string out = std::to_string(all.size()) + (all.size() == 1 ? " change:" : " changes:");
  for (const auto& change : all) out += "\n  " + describeChange(change);
  return out;
}

std::vector<WorkingMemoryChange> ChangeCollector::waitForCount(std::size_t count, std::chrono::milliseconds timeout) {
  const std::string noun = std::to_string(count) + (count == 1 ? " change" : " changes");
  waitFor([&] { return size() >= count; }, timeout, noun, [&] { return describe(); });
  const auto all = changes();
  return std::vector<WorkingMemoryChange>(all.begin(), all.begin() + static_cast<std::ptrdiff_t>(count));
}

WorkingMemoryChange ChangeCollector::waitForChange(const std::function<bool(const WorkingMemoryChange&)>& test,
                                                   std::chrono::milliseconds timeout, const std::string& what) {
  std::optional<WorkingMemoryChange> found;
  waitFor(
      [&] {
        for (const auto& change : changes()) {
          if (test(change)) {
            found = change;
            return true;
          }
        }
        return false;
      },
      timeout, what, [&] { return describe(); });
  return *found;
}

void ChangeCollector::clear() {
  std::lock_guard<std::mutex> lock(mu_);
  changes_.clear();
}

void ChangeCollector::close() {
  if (watcher_) watcher_->close();
}

// ------------------------------------------------------------------ RunningComponent

RunningComponentBase::RunningComponentBase(Component& component, std::string componentId)
    : component_(component), componentId_(std::move(componentId)) {}

RunningComponentBase::~RunningComponentBase() { finish(); }

void RunningComponentBase::begin(std::shared_ptr<cast::detail::Transport> transport, Args args) {
  thread_ = std::thread([this, transport = std::move(transport), args = std::move(args)] {
    int code = 1;
    std::exception_ptr error;
    try {
      code = runComponent(component_, transport, args, /*handleSignals=*/false, /*startBarrier=*/false, [this] {
        {
          std::lock_guard<std::mutex> lock(mu_);
          started_ = true;
        }
        cv_.notify_all();
      });
    } catch (...) {  // binding failed (a refused token, a server away): the test hears of it
      error = std::current_exception();
    }
    {
      std::lock_guard<std::mutex> lock(mu_);
      error_ = error;
      exitCode_ = code;
      started_ = ended_ = true;
    }
    cv_.notify_all();
  });
}

void RunningComponentBase::waitStarted(std::chrono::milliseconds timeout) {
  std::unique_lock<std::mutex> lock(mu_);
  if (!cv_.wait_for(lock, timeout, [this] { return started_; })) {
    throw AssertionError(componentId_ + ": start() did not return within " + seconds(timeout) + " s");
  }
  if (error_) std::rethrow_exception(error_);
}

bool RunningComponentBase::running() const {
  std::lock_guard<std::mutex> lock(mu_);
  return !ended_;
}

std::optional<int> RunningComponentBase::exitCode() const {
  std::lock_guard<std::mutex> lock(mu_);
  return exitCode_;
}

int RunningComponentBase::join(std::chrono::milliseconds timeout) {
  {
    std::unique_lock<std::mutex> lock(mu_);
    if (!cv_.wait_for(lock, timeout, [this] { return ended_; })) {
      throw AssertionError(componentId_ + " did not stop by itself within " + seconds(timeout) + " s");
    }
  }
  if (thread_.joinable()) thread_.join();
  return exitCode_.value_or(1);
}

int RunningComponentBase::stop(std::chrono::milliseconds timeout) {
  if (running()) component_.requestStop();
  // The runner gives run() 10 s and the queued callbacks 5 s after the request.
  return join(timeout + std::chrono::seconds(15));
}

void RunningComponentBase::finish() {
  if (!thread_.joinable()) return;
  if (running()) component_.requestStop();
  thread_.join();
}

// ------------------------------------------------------------------ LocalSystem

LocalSystem::LocalSystem(std::initializer_list<std::string> subarchitectures)
    : LocalSystem(SystemOptions{std::vector<std::string>(subarchitectures), "", {}, std::chrono::seconds(90)}) {}

LocalSystem::LocalSystem(SystemOptions options) {
  if (!options.config.empty() && !options.subarchitectures.empty()) {
    throw InvalidArgumentError("give SystemOptions a configuration or subarchitectures, not both: the configuration "
                               "names its own subarchitectures");
  }
  std::string config;
  if (!options.config.empty()) {
    config = std::filesystem::absolute(options.config).string();
    if (!std::filesystem::is_regular_file(config)) {
      throw NotFoundError("no configuration file " + config + ": give the path of a system's YAML file");
    }
  }
  const std::vector<std::string> command = detail::findCast();  // before anything is made: nothing to clean
  directory_ = newDirectory();
  try {
    if (config.empty()) {
      std::vector<std::string> sas = options.subarchitectures;
      if (sas.empty()) sas = {"vision", "language"};
      config = directory_ + "/system.yaml";
      std::ofstream out(config);
      out << "system: test\nsubarchitectures:\n";
      for (const auto& sa : sas) out << "  " << quoted(sa) << ": {}\n";
    }
    const std::string secretFile = directory_ + "/secret";
    secret_ = newSecret(secretFile);
    std::vector<std::string> args = {config, "--secret-file", secretFile};
    for (const auto& [name, value] : options.sets) {
      args.emplace_back("--set");
      args.push_back(name + "=" + value);
    }
    server_ = std::make_unique<detail::ServeProcess>(command, directory_, args, options.startTimeout);
    // The name and SAs as the server has them (the configuration is YAML, which only the server reads).
    cast::v1::SystemDescription description;
    grpc::ClientContext context;
    context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(30));
    context.AddMetadata("authorization", "Bearer " + token(kObserver, ""));
    const grpc::Status status = cast::v1::Directory::NewStub(channelTo(endpoint()))
                                    ->DescribeSystem(&context, cast::v1::DescribeSystemRequest(), &description);
    if (!status.ok()) {
      throw UnavailableError("the test's server did not describe its system (" + status.error_message() +
                             "); it printed:\n" + server_->output());
    }
    name_ = description.name();
    for (const auto& sa : description.subarchitectures()) subarchitectures_.push_back(sa.name());
  } catch (...) {
    server_.reset();
    std::filesystem::remove_all(directory_);
    throw;
  }
}

LocalSystem::~LocalSystem() {
  try {
    close();
  } catch (...) {  // a destructor must not throw
  }
}

const std::string& LocalSystem::endpoint() const { return server_->endpoint(); }

std::string LocalSystem::token(const std::string& componentId, const std::string& subarchitecture,
                               bool privileged) const {
  return mintToken(secret_, Identity{componentId, subarchitecture, privileged},
                   static_cast<std::int64_t>(std::time(nullptr)));
}

std::map<std::string, std::string> LocalSystem::launchEnvironment(const std::string& componentId,
                                                                  const std::string& subarchitecture,
                                                                  const Args& args, bool privileged) const {
  return {{"CAST_ENDPOINT", endpoint()},
          {"CAST_COMPONENT_ID", componentId},
          {"CAST_SUBARCHITECTURE", subarchitecture},
          {"CAST_TOKEN", token(componentId, subarchitecture, privileged)},
          {"CAST_ARGS", args.toJson()}};
}

std::shared_ptr<cast::detail::Transport> LocalSystem::transport(const std::string& componentId,
                                                                const std::string& subarchitecture,
                                                                bool privileged) {
  if (closed_) throw InvalidArgumentError("system '" + name_ + "' is closed: start another one");
  if (std::find(subarchitectures_.begin(), subarchitectures_.end(), subarchitecture) == subarchitectures_.end()) {
    std::string known;
    for (const auto& sa : subarchitectures_) known += (known.empty() ? "" : ", ") + sa;
    throw InvalidArgumentError("no subarchitecture '" + subarchitecture + "' in system '" + name_ + "' (it has " +
                               known + ")");
  }
  return connectGrpc(endpoint(), token(componentId, subarchitecture, privileged),
                     Identity{componentId, subarchitecture, privileged});
}

Actor& LocalSystem::actAs(const std::string& componentId, const std::string& subarchitecture, bool privileged) {
  auto actor = std::make_unique<Actor>();
  Actor& made = *actor;
  made.bind(transport(componentId, subarchitecture, privileged));
  components_.push_back(std::move(actor));
  return made;
}

Actor& LocalSystem::observer() {
  if (observer_ == nullptr) observer_ = &actAs(kObserver, subarchitectures_.front(), true);
  return *observer_;
}

ChangeCollector& LocalSystem::collectChanges(const std::vector<ChangeFilter>& filters,
                                             const std::string& subarchitecture) {
  const std::string sa = subarchitecture.empty() ? subarchitectures_.front() : subarchitecture;
  std::unique_ptr<ChangeCollector> collector(new ChangeCollector());
  ChangeCollector* target = collector.get();
  collector->watcher_ =
      connect(transport(std::string(kObserver) + "-changes-" + std::to_string(collectors_.size() + 1), sa, true));
  collectors_.push_back(std::move(collector));
  const std::vector<ChangeFilter> chosen =
      filters.empty() ? std::vector<ChangeFilter>{operationFilter({}, false, true)} : filters;
  target->watcher_->onChange(chosen, [target](const WorkingMemoryChange& change) { target->collect(change); });
  return *target;
}

std::string LocalSystem::where(const std::string& subarchitecture, const std::string& id) {
  return "entry '" + id + "' in subarchitecture '" + subarchitecture + "'";
}

std::string LocalSystem::describeEntry(const google::protobuf::Message& value, std::uint64_t version,
                                       const std::string& author) {
  return describeValue(value) + " (version " + std::to_string(version) + ", by " + author + ")";
}

bool LocalSystem::sameValue(const google::protobuf::Message& a, const google::protobuf::Message& b) {
  return google::protobuf::util::MessageDifferencer::Equals(a, b);
}

std::string LocalSystem::listEntries(const std::string& subarchitecture) const {
  cast::v1::ListEntriesRequest request;
  request.set_subarchitecture(subarchitecture);
  cast::v1::ListEntriesResponse listing;
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + std::chrono::seconds(10));
  context.AddMetadata("authorization", "Bearer " + token(kObserver, subarchitecture));
  const grpc::Status status =
      cast::v1::Inspection::NewStub(channelTo(endpoint()))->ListEntries(&context, request, &listing);
  if (!status.ok()) return "its entries could not be listed (" + status.error_message() + ")";
  if (listing.entries_size() == 0) return "that WM is empty";
  std::string out = "entries there: ";
  int shown = 0;
  for (const auto& entry : listing.entries()) {
    if (shown == 20) return out + ", ...";
    out += (shown++ == 0 ? "" : ", ") + entry.address().id() + " (" + entry.type() + ")";
  }
  return out;
}

std::string LocalSystem::output() const { return closed_ ? output_ : server_->output(); }

void LocalSystem::kill() {
  if (closed_) throw InvalidArgumentError("system '" + name_ + "' is closed: start another one");
  server_->kill();
}

void LocalSystem::restart() {
  if (closed_) throw InvalidArgumentError("system '" + name_ + "' is closed: start another one");
  server_->restart();
}

int LocalSystem::close() {
  if (closed_) return exitCode_;
  closed_ = true;
  for (auto it = running_.rbegin(); it != running_.rend(); ++it) {
    try {
      (*it)->stop();
    } catch (const AssertionError&) {  // one that does not stop is the test's to see in its exit code and log
    }
  }
  for (auto& collector : collectors_) collector->close();
  for (auto it = components_.rbegin(); it != components_.rend(); ++it) (*it)->close();
  exitCode_ = server_->stop();
  output_ = server_->output();  // the log goes with the directory
  std::error_code ignored;
  std::filesystem::remove_all(directory_, ignored);
  return exitCode_;
}

}  // namespace cast::testing
