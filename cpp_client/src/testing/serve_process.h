// `cast serve` as a process of the test (cast/testing.h): finding the
// command, starting it on a free port, reading the address it listens on,
// stopping it.
#pragma once

#include <sys/types.h>

#include <chrono>
#include <string>
#include <vector>

namespace cast::testing::detail {

// The command that runs `cast`: $CAST_SERVE, else `cast` on PATH, else
// python3 -m cast.cli when python3 has the package. NotFoundError saying what
// to install when there is none.
std::vector<std::string> findCast();

class ServeProcess {
 public:
  // Starts `COMMAND serve CONFIG --secret-file SECRET --exit-with-stdin ARGS --listen 127.0.0.1:0`
  // in `directory`, its output to directory/server.log, and waits for its
  // "listening on HOST:PORT" line; UnavailableError with the output if it
  // does not come within `startTimeout`.
  ServeProcess(std::vector<std::string> command, std::string directory, std::vector<std::string> serveArgs,
               std::chrono::milliseconds startTimeout);
  ~ServeProcess();
  ServeProcess(const ServeProcess&) = delete;
  ServeProcess& operator=(const ServeProcess&) = delete;

  const std::string& endpoint() const { return endpoint_; }
  pid_t pid() const { return pid_; }
  // What the servers started so far printed.
  std::string output() const;
  // SIGTERM (the clean shutdown), SIGKILL after 30 s; the exit status (a
  // signal as its negative number). 0 if it was not running.
  int stop();
  // SIGKILL.
  void kill();
  // kill(), then a new server on the same address.
  void restart();

 private:
  void start(const std::string& listen);
  int end(int signal, std::chrono::milliseconds grace);
  std::vector<std::string> argv_;
  std::string directory_;
  std::string log_;
  std::chrono::milliseconds startTimeout_;
  pid_t pid_ = -1;
  int stdin_ = -1;  // the write end of the server's standard input: its lifeline
  std::string endpoint_;
};

}  // namespace cast::testing::detail
