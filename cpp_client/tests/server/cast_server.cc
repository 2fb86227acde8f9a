// A real `cast serve` for tests (cast_server.h).
#include "cast_server.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdlib>
#include <ctime>
#include <fstream>
#include <sstream>
#include <stdexcept>
#include <thread>

#include "cast/credentials.h"

namespace cast::testing {

namespace {

// The secret the server signs with (the pytest suites use the same one).
constexpr char kSecret[] = "test-secret-0123456789abcdef-0123456789";
constexpr char kListening[] = "listening on ";

std::string castExecutable() {
  const std::string path = std::string(CAST_REPO_ROOT) + "/.venv/bin/cast";
  if (::access(path.c_str(), X_OK) != 0) {
    throw std::runtime_error(path + " is missing: these tests run the repository's Python server; run `make setup proto` "
                             "first (make test-cpp does)");
  }
  return path;
}

std::string readFile(const std::string& path) {
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

}  // namespace

CastServer::CastServer(std::vector<std::string> subarchitectures) {
  char pattern[] = "/tmp/cast-cpp-server-XXXXXX";
  if (::mkdtemp(pattern) == nullptr) throw std::runtime_error("mkdtemp failed");
  dir_ = pattern;
  std::ofstream config(dir_ + "/system.yaml");
  config << "system: cpp-tests\nsubarchitectures:\n";
  for (const auto& sa : subarchitectures) config << "  " << sa << ": {}\n";
  config.close();
  start("127.0.0.1:0");
}

CastServer::~CastServer() {
  if (pid_ > 0) {
    ::kill(pid_, SIGTERM);
    for (int i = 0; i < 500; ++i) {
      if (::waitpid(pid_, nullptr, WNOHANG) == pid_) {
        pid_ = -1;
        break;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    kill();
  }
  std::system(("rm -rf '" + dir_ + "'").c_str());
}

void CastServer::start(const std::string& listen) {
  const std::string cast = castExecutable();
  const std::string logPath = dir_ + "/server.log";
  // Everything the child needs is built before fork(): between fork and exec
  // it may only make system calls (the test process has threads).
  std::vector<std::string> args = {cast, "serve", dir_ + "/system.yaml", "--listen", listen};
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  std::vector<std::string> env;
  for (char** e = environ; *e != nullptr; ++e) {
    if (std::string(*e).rfind("CAST_", 0) != 0) env.emplace_back(*e);
  }
  env.push_back(std::string("CAST_SECRET=") + kSecret);
  std::vector<char*> envp;
  for (auto& e : env) envp.push_back(e.data());
  envp.push_back(nullptr);
  // After a restart the log holds the first start's line too: only what
  // this start prints counts.
  const std::size_t from = readFile(logPath).size();
  const pid_t parent = ::getpid();
  const pid_t pid = ::fork();
  if (pid < 0) throw std::runtime_error("fork failed");
  if (pid == 0) {
    ::prctl(PR_SET_PDEATHSIG, SIGKILL);  // no server outlives a test binary that crashed
    if (::getppid() != parent) ::_exit(127);
    const int out = ::open(logPath.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
    if (out >= 0) {
      ::dup2(out, 1);
      ::dup2(out, 2);
    }
    if (::chdir(dir_.c_str()) != 0) ::_exit(127);
    ::execve(argv[0], argv.data(), envp.data());
    ::_exit(127);
  }
  pid_ = pid;
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(30);
  while (std::chrono::steady_clock::now() < deadline) {
    const std::string all = readFile(logPath);
    const std::string text = all.size() > from ? all.substr(from) : std::string();
    const auto at = text.rfind(kListening);
    const auto eol = at == std::string::npos ? std::string::npos : text.find('\n', at);
    if (eol != std::string::npos) {
      endpoint_ = text.substr(at + sizeof(kListening) - 1, eol - at - (sizeof(kListening) - 1));
      return;
    }
    if (::waitpid(pid_, nullptr, WNOHANG) == pid_) {
      pid_ = -1;
      throw std::runtime_error("cast serve exited before listening:\n" + text);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  kill();
  throw std::runtime_error("cast serve did not listen within 30 s:\n" + readFile(logPath));
}

std::string CastServer::token(const std::string& componentId, const std::string& sa, bool privileged,
                              const std::string& secret) const {
  return mintToken(secret.empty() ? kSecret : secret, Identity{componentId, sa, privileged},
                   static_cast<std::int64_t>(std::time(nullptr)));
}

std::unique_ptr<Connection> CastServer::connect(const std::string& componentId, const std::string& sa,
                                                TransportOptions options) const {
  return cast::connect(connectGrpc(endpoint_, token(componentId, sa), Identity{componentId, sa, false}, options));
}

void CastServer::kill() {
  if (pid_ <= 0) return;
  ::kill(pid_, SIGKILL);
  ::waitpid(pid_, nullptr, 0);
  pid_ = -1;
}

void CastServer::restart() {
  kill();
  start(endpoint_);
}

std::string CastServer::log() const { return readFile(dir_ + "/server.log"); }

CastServer& sharedServer() {
  static CastServer server;
  return server;
}

bool waitFor(const std::function<bool()>& condition, std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (!condition()) {
    if (std::chrono::steady_clock::now() >= deadline) return condition();
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return true;
}

}  // namespace cast::testing
