// `cast serve` as a process of the test (serve_process.h).
#include "serve_process.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <fstream>
#include <sstream>
#include <thread>

#include "cast/errors.h"

extern char** environ;

namespace cast::testing::detail {

namespace {

constexpr char kListening[] = "listening on ";

bool executable(const std::string& path) {
  struct stat st {};
  return ::stat(path.c_str(), &st) == 0 && S_ISREG(st.st_mode) && ::access(path.c_str(), X_OK) == 0;
}

// `name` as PATH finds it; empty if it does not.
std::string onPath(const std::string& name) {
  const char* path = std::getenv("PATH");
  std::stringstream dirs(path != nullptr ? path : "");
  for (std::string dir; std::getline(dirs, dir, ':');) {
    const std::string candidate = (dir.empty() ? "." : dir) + "/" + name;
    if (executable(candidate)) return candidate;
  }
  return "";
}

std::string readFile(const std::string& path) {
  std::ifstream in(path);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

// This process's environment without the launch contract of a component: the
// server is not one.
std::vector<std::string> childEnvironment() {
  std::vector<std::string> env;
  for (char** e = environ; e != nullptr && *e != nullptr; ++e) {
    if (std::string(*e).rfind("CAST_", 0) != 0) env.emplace_back(*e);
  }
  return env;
}

std::vector<char*> pointers(std::vector<std::string>& strings) {
  std::vector<char*> out;
  for (auto& s : strings) out.push_back(s.data());
  out.push_back(nullptr);
  return out;
}

// Runs `argv` with its output thrown away; whether it exited 0.
bool succeeds(std::vector<std::string> argv) {
  std::vector<char*> args = pointers(argv);
  const pid_t pid = ::fork();
  if (pid < 0) return false;
  if (pid == 0) {
    const int null = ::open("/dev/null", O_RDWR);
    if (null >= 0) {
      ::dup2(null, 0);
      ::dup2(null, 1);
      ::dup2(null, 2);
    }
    ::execv(args[0], args.data());
    ::_exit(127);
  }
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  return WIFEXITED(status) && WEXITSTATUS(status) == 0;
}

int exitStatus(int status) { return WIFEXITED(status) ? WEXITSTATUS(status) : -WTERMSIG(status); }

}  // namespace

std::vector<std::string> findCast() {
  if (const char* given = std::getenv("CAST_SERVE"); given != nullptr && *given != '\0') {
    if (!executable(given)) {
      throw NotFoundError(std::string("CAST_SERVE names ") + given +
                          ", which is not an executable file: set it to the `cast` command of the installed Python "
                          "package cast-grpc (pip install cast-grpc), or unset it to use `cast` on PATH");
    }
    return {given};
  }
  if (std::string cast = onPath("cast"); !cast.empty()) return {cast};
  if (std::string python = onPath("python3"); !python.empty() && succeeds({python, "-c", "import cast.cli"})) {
    return {python, "-m", "cast.cli"};
  }
  throw NotFoundError(
      "cast::testing runs the CAST server, `cast serve`, and found none: not in CAST_SERVE, not `cast` on PATH, "
      "not the Python package in python3; install it with `pip install cast-grpc` (docs/packages.md) into an "
      "environment whose bin/ is on PATH, or set CAST_SERVE to its `cast` executable");
}

ServeProcess::ServeProcess(std::vector<std::string> command, std::string directory,
                           std::vector<std::string> serveArgs, std::chrono::milliseconds startTimeout)
    : argv_(std::move(command)),
      directory_(std::move(directory)),
      log_(directory_ + "/server.log"),
      startTimeout_(startTimeout) {
  argv_.emplace_back("serve");
  argv_.insert(argv_.end(), serveArgs.begin(), serveArgs.end());
  argv_.emplace_back("--exit-with-stdin");
  start("127.0.0.1:0");
}

ServeProcess::~ServeProcess() { stop(); }

void ServeProcess::start(const std::string& listen) {
  // Everything the child needs is made before fork(): between fork and exec
  // it may only make system calls (the test process has threads).
  std::vector<std::string> args = argv_;
  args.emplace_back("--listen");
  args.push_back(listen);
  std::vector<char*> argv = pointers(args);
  std::vector<std::string> env = childEnvironment();
  std::vector<char*> envp = pointers(env);
  int lifeline[2];
  // Close-on-exec: no other child of the test inherits the write end and keeps the server alive.
  if (::pipe2(lifeline, O_CLOEXEC) != 0) throw UnavailableError("cannot make a pipe for `cast serve`");
  // After a restart the log holds the earlier servers' lines: only what this one prints counts.
  const std::size_t from = readFile(log_).size();
  const pid_t pid = ::fork();
  if (pid < 0) {
    ::close(lifeline[0]);
    ::close(lifeline[1]);
    throw UnavailableError("cannot fork to start `cast serve`");
  }
  if (pid == 0) {
    ::dup2(lifeline[0], 0);
    const int out = ::open(log_.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
    if (out >= 0) {
      ::dup2(out, 1);
      ::dup2(out, 2);
    }
    if (::chdir(directory_.c_str()) != 0) ::_exit(127);
    ::execve(argv[0], argv.data(), envp.data());
    ::_exit(127);
  }
  ::close(lifeline[0]);
  pid_ = pid;
  stdin_ = lifeline[1];
  const auto deadline = std::chrono::steady_clock::now() + startTimeout_;
  while (std::chrono::steady_clock::now() < deadline) {
    const std::string all = readFile(log_);
    const std::string text = all.size() > from ? all.substr(from) : std::string();
    const auto at = text.find(kListening);
    const auto eol = at == std::string::npos ? std::string::npos : text.find('\n', at);
    if (eol != std::string::npos) {
      endpoint_ = text.substr(at + sizeof(kListening) - 1, eol - at - (sizeof(kListening) - 1));
      return;
    }
    int status = 0;
    if (::waitpid(pid_, &status, WNOHANG) == pid_) {
      pid_ = -1;
      ::close(stdin_);
      stdin_ = -1;
      throw UnavailableError("`" + argv_[0] + " serve` exited (status " + std::to_string(exitStatus(status)) +
                             ") before it listened; it printed:\n" + text);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  kill();
  throw UnavailableError("`" + argv_[0] + " serve` did not say it listens within " +
                         std::to_string(startTimeout_.count() / 1000) + " s; it printed:\n" + readFile(log_));
}

int ServeProcess::end(int signal, std::chrono::milliseconds grace) {
  if (stdin_ >= 0) {
    ::close(stdin_);
    stdin_ = -1;
  }
  if (pid_ <= 0) return 0;
  ::kill(pid_, signal);
  const auto deadline = std::chrono::steady_clock::now() + grace;
  int status = 0;
  while (true) {
    const pid_t done = ::waitpid(pid_, &status, WNOHANG);
    if (done == pid_ || (done < 0 && errno != EINTR)) break;
    if (std::chrono::steady_clock::now() >= deadline) {
      ::kill(pid_, SIGKILL);
      while (::waitpid(pid_, &status, 0) < 0 && errno == EINTR) {
      }
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  pid_ = -1;
  return exitStatus(status);
}

int ServeProcess::stop() { return end(SIGTERM, std::chrono::seconds(30)); }

void ServeProcess::kill() { end(SIGKILL, std::chrono::seconds(30)); }

void ServeProcess::restart() {
  kill();
  start(endpoint_);
}

std::string ServeProcess::output() const { return readFile(log_); }

}  // namespace cast::testing::detail
