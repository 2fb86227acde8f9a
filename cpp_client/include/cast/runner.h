// Running a component: the launch contract (docs/design.md section 6) and the
// lifecycle (docs/client-protocol.md, "Start-up").
//
//   class Segmenter : public cast::UnmanagedComponent { ... };
//   CAST_COMPONENT_MAIN(Segmenter)
//
// makes an executable that reads CAST_ENDPOINT, CAST_COMPONENT_ID,
// CAST_SUBARCHITECTURE, its token (the file CAST_TOKEN_FILE names, re-read
// when renewed, when that is set; else CAST_TOKEN), CAST_ARGS (a JSON object)
// and optionally CAST_TLS_* (see cast/credentials.h), connects,
// calls configure(args), start(), run() (with CAST_START_BARRIER=1, as `cast
// run` launches it, run() waits until every component of the system has
// finished start(), so a watch made in start() misses nothing another
// component writes in run()), and stop() once on SIGINT/SIGTERM,
// on requestStop(), or when a hook threw. Exit codes: 0 ok, 1 the component
// failed, 2 bad launch environment (missing variables, an empty or unreadable
// CAST_TOKEN_FILE, bad CAST_ARGS, a system that refuses the token or does not
// answer within the connect window, or a token the server verified as another
// component or SA than CAST_COMPONENT_ID and CAST_SUBARCHITECTURE name).
#pragma once

#include <chrono>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>

#include "cast/args.h"
#include "cast/basic_types.h"
#include "cast/component.h"
#include "cast/credentials.h"
#include "cast/grpc_transport.h"

namespace cast {

// How long a launched component keeps asking a server that does not answer
// before it gives up (LaunchContract::connect; CONNECT_WINDOW_S in Python).
inline constexpr std::chrono::seconds kConnectWindow{20};

// The environment a component process is started with.
struct LaunchContract {
  std::string endpoint;
  std::string componentId;
  std::string subarchitecture;
  std::string token;
  Args args;
  std::string tokenFile;          // CAST_TOKEN_FILE: re-read when the orchestrator renews the token
  std::optional<ClientTls> tls;   // CAST_TLS_CA / CAST_TLS_CERT / CAST_TLS_KEY / CAST_TLS_SERVER_NAME
  bool startBarrier = false;      // CAST_START_BARRIER=1: run() waits until every component has started
  // CAST_CONNECT_WINDOW_S: how long the first contact is asked again (default kConnectWindow).
  std::chrono::milliseconds connectWindow = kConnectWindow;

  // Reads the contract from the process environment; InvalidArgumentError
  // naming every missing variable, or saying what is wrong with CAST_ARGS or
  // with the file CAST_TOKEN_FILE names (empty, unreadable).
  static LaunchContract fromEnv();
  // The same from a given environment (for tests).
  static LaunchContract fromEnv(const std::map<std::string, std::string>& env);

  // The component's identity as the environment states it, not privileged:
  // the token is not decoded here. Component::bind learns the privilege from
  // the server, which verifies the token at Register, and refuses to start
  // if the server's identity is another (the runner then exits 2).
  Identity identity() const;
  // A gRPC connection to the system. Whoever launched the component started
  // the system first, so a server that does not answer at once is busy or
  // still starting: a first call failing with UNAVAILABLE or
  // DEADLINE_EXCEEDED is asked again with backoff for `window`, then
  // UnavailableError saying where it asked, for how long and what to check.
  // Any other failure is thrown at once. SIGINT/SIGTERM caught by the runner
  // end the waiting (CastError with code CANCELLED).
  std::shared_ptr<detail::Transport> connect(std::chrono::milliseconds window = kConnectWindow) const;
};

// Runs a bound-to-be component to the end and returns the exit code (0 ok,
// 1 failed). run() executes on a worker thread so that a signal can call
// stop() while run() is busy. With handleSignals, SIGINT and SIGTERM ask
// the component to stop. With startBarrier (a component `cast run`
// launched), the component reports STARTED after start() and run() waits
// for the system's start barrier (Transport::awaitRun); asked to stop while
// waiting, it skips run() (stop() is still called once). `onStarted`, if
// given, is called once on the lifecycle's thread when run() is about to begin
// (start() returned: its watches are registered), or when the lifecycle ended
// before that (a hook threw, or the component was stopped first): what
// cast::testing waits for before it hands a running component to a test.
int runComponent(Component& component, std::shared_ptr<detail::Transport> transport, const Args& args,
                 bool handleSignals = true, bool startBarrier = false,
                 const std::function<void()>& onStarted = nullptr);

// The whole main(): reads the launch environment, makes the component, runs it.
int runMain(const std::function<std::unique_ptr<Component>()>& factory, int argc, char** argv);

}  // namespace cast

// Defines main() for a component class (default-constructible).
#define CAST_COMPONENT_MAIN(ComponentClass)                                                   \
  int main(int argc, char** argv) {                                                           \
    return ::cast::runMain([] { return std::unique_ptr<::cast::Component>(new ComponentClass()); }, argc, argv); \
  }
