#include "cast/runner.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdlib>
#include <cstring>
#include <future>
#include <iostream>
#include <mutex>
#include <thread>

#include "cast/grpc_transport.h"
#include "cast/log.h"
#include "component_core.h"
#include "connect_resolve.h"
#include "connect_window.h"
#include "process_env.h"

extern char** environ;

namespace cast {

std::map<std::string, std::string> detail::processEnv() {
  std::map<std::string, std::string> env;
  for (char** e = environ; e != nullptr && *e != nullptr; ++e) {
    const char* eq = std::strchr(*e, '=');
    if (eq != nullptr) env.emplace(std::string(*e, static_cast<std::size_t>(eq - *e)), std::string(eq + 1));
  }
  return env;
}

namespace {

// Set from the signal handler; polled by the main thread. A lock-free atomic
// is the only thing a handler may safely touch.
std::atomic<bool> g_signalled{false};
static_assert(std::atomic<bool>::is_always_lock_free);

extern "C" void onSignal(int) { g_signalled.store(true); }

void installSignalHandlers() {
  struct sigaction sa {};
  sa.sa_handler = onSignal;
  sigemptyset(&sa.sa_mask);
  sa.sa_flags = 0;
  sigaction(SIGINT, &sa, nullptr);
  sigaction(SIGTERM, &sa, nullptr);
}

std::string describe(const std::exception_ptr& ep) {
  try {
    std::rethrow_exception(ep);
  } catch (const CastError& e) {
    return std::string(e.name()) + ": " + e.message();
  } catch (const std::exception& e) {
    return e.what();
  } catch (...) {
    return "a non-standard exception";
  }
}

}  // namespace

LaunchContract LaunchContract::fromEnv() { return fromEnv(detail::processEnv()); }

LaunchContract LaunchContract::fromEnv(const std::map<std::string, std::string>& env) {
  auto get = [&](const char* name) {
    auto it = env.find(name);
    return it == env.end() ? std::string() : it->second;
  };
  std::string missing;
  auto lacks = [&missing](const std::string& what) { missing += (missing.empty() ? "" : ", ") + what; };
  for (const char* name : {"CAST_ENDPOINT", "CAST_COMPONENT_ID", "CAST_SUBARCHITECTURE"}) {
    if (get(name).empty()) lacks(name);
  }
  if (get("CAST_TOKEN").empty() && get("CAST_TOKEN_FILE").empty()) lacks("CAST_TOKEN or CAST_TOKEN_FILE");
  if (!missing.empty()) {
    throw InvalidArgumentError("missing launch environment: " + missing +
                               "; start the component with `cast run CONFIG`, or get the variables from `cast token`");
  }
  LaunchContract c;
  c.endpoint = get("CAST_ENDPOINT");
  c.componentId = get("CAST_COMPONENT_ID");
  c.subarchitecture = get("CAST_SUBARCHITECTURE");
  c.args = Args::fromJson(get("CAST_ARGS"));
  c.tokenFile = get("CAST_TOKEN_FILE");
  // The file is the renewed token: when it is set, it is the token (as for cast::connect).
  c.token = c.tokenFile.empty() ? get("CAST_TOKEN") : detail::readTokenFile(c.tokenFile);
  c.tls = ClientTls::fromEnv(env);
  c.startBarrier = get("CAST_START_BARRIER") == "1";
  const std::string window = get("CAST_CONNECT_WINDOW_S");
  if (!window.empty()) {
    // Same rule and words as Python's connect_window_from: seconds, 0 or more.
    char* end = nullptr;
    const double seconds = std::strtod(window.c_str(), &end);
    if (end == window.c_str() || *end != '\0' || !(seconds >= 0) || !std::isfinite(seconds)) {
      throw InvalidArgumentError("CAST_CONNECT_WINDOW_S '" + window +
                                 "': give the seconds a launched component keeps asking a server that does not "
                                 "answer, 0 or more (default 20)");
    }
    c.connectWindow = std::chrono::milliseconds(static_cast<long long>(seconds * 1000));
  }
  return c;
}

Identity LaunchContract::identity() const { return Identity{componentId, subarchitecture, false}; }

std::shared_ptr<detail::Transport> LaunchContract::connect(std::chrono::milliseconds window) const {
  TransportOptions options;
  options.tokenFile = tokenFile;
  options.tls = tls;
  detail::ConnectClock clock;
  // Waits in short steps so that a SIGTERM from the launcher ends the asking
  // at once rather than after the window.
  clock.wait = [](detail::Millis delay) {
    const auto until = std::chrono::steady_clock::now() + delay;
    while (!g_signalled.load()) {
      const auto left = until - std::chrono::steady_clock::now();
      if (left <= std::chrono::steady_clock::duration::zero()) return false;
      std::this_thread::sleep_for(std::min<std::chrono::steady_clock::duration>(left, std::chrono::milliseconds(50)));
    }
    return true;
  };
  return detail::connectWithin<std::shared_ptr<detail::Transport>>(
      endpoint, tls.has_value(), window, [&] { return connectGrpc(endpoint, token, identity(), options); }, clock,
      Logger("cast.run"));
}

int runComponent(Component& component, std::shared_ptr<detail::Transport> transport, const Args& args,
                 bool handleSignals, bool startBarrier, const std::function<void()>& onStarted) {
  if (handleSignals) installSignalHandlers();
  component.bind(transport);
  const Logger& log = component.log();
  std::atomic<bool> failed{false};
  std::atomic<bool> stopCalled{false};

  // stop() exactly once, whoever asks first.
  auto stopOnce = [&] {
    if (stopCalled.exchange(true)) return;
    component.setState(ComponentState::Stopping);
    component.requestStop();
    try {
      component.stop();
    } catch (...) {
      log.error("stop() failed: " + describe(std::current_exception()));
      failed = true;
    }
  };

  std::promise<void> runDone;
  auto runFinished = runDone.get_future();
  std::once_flag saidStarted;
  auto sayStarted = [&] {
    if (onStarted) std::call_once(saidStarted, onStarted);
  };
  std::thread worker([&] {
    try {
      component.configure(args);
      component.start();
      // Watches made in start() are registered by now (onChange returns once
      // the servers confirmed them): say so, and run() only once every
      // component has, so none misses what another writes first thing in run().
      bool go = true;
      if (startBarrier) {
        component.setState(ComponentState::Started);
        go = transport->awaitRun([&](std::chrono::milliseconds d) { return component.waitForStop(d); });
      }
      // Not released: asked to stop before the system got going; stop()
      // follows, run() never runs.
      if (go) {
        component.setState(ComponentState::Running);
        sayStarted();
        component.run();
      }
    } catch (...) {
      log.error("failed: " + describe(std::current_exception()));
      failed = true;
      stopOnce();
    }
    sayStarted();  // also when the lifecycle ended before run(): nobody waits forever
    runDone.set_value();
  });

  using namespace std::chrono_literals;
  while (!component.waitForStop(200ms)) {
    if (g_signalled.load()) {
      log.info("signal received: stopping");
      break;
    }
    if (failed && runFinished.wait_for(0ms) == std::future_status::ready) break;
  }
  stopOnce();
  if (runFinished.wait_for(10s) != std::future_status::ready) {
    // run() ignores the stop request: nothing can end a thread from outside,
    // so end the process (the server releases our session when it goes).
    log.error("run() did not return within 10 s of stop(): exiting anyway");
    std::_Exit(1);
  }
  worker.join();
  // Callbacks queued before the stop still run, then the session ends.
  component.drain(5000ms);
  component.close();
  return failed ? 1 : 0;
}

int runMain(const std::function<std::unique_ptr<Component>()>& factory, int argc, char** argv) {
  if (argc > 1 && (std::strcmp(argv[1], "-h") == 0 || std::strcmp(argv[1], "--help") == 0)) {
    std::cout << "usage: " << argv[0]
              << "   (reads CAST_ENDPOINT, CAST_COMPONENT_ID, CAST_SUBARCHITECTURE, CAST_TOKEN_FILE or CAST_TOKEN\n"
                 "   and CAST_ARGS from the environment; `cast run CONFIG` sets them, `cast token` prints them)\n";
    return 0;
  }
  // Signals are caught from the start, so a SIGTERM that arrives while
  // connecting still ends the process in order.
  installSignalHandlers();
  LaunchContract contract;
  std::shared_ptr<detail::Transport> transport;
  try {
    contract = LaunchContract::fromEnv();
    transport = contract.connect(contract.connectWindow);
  } catch (const CastError& e) {
    std::cerr << "cast: " << e.message() << std::endl;
    // A stop asked for while the server did not answer yet is honoured, not a failure.
    return e.code() == "CANCELLED" && g_signalled.load() ? 0 : 2;
  }
  std::unique_ptr<Component> component;
  try {
    component = factory();
  } catch (...) {
    std::cerr << "cast: constructing the component failed: " << describe(std::current_exception()) << std::endl;
    transport->close();
    return 1;
  }
  try {
    return runComponent(*component, std::move(transport), contract.args, true, contract.startBarrier);
  } catch (const detail::IdentityMismatchError& e) {
    // bind() found that the token is another component's: the launch
    // environment is wrong, not the component (bind already closed the connection).
    std::cerr << "cast: " << e.message() << std::endl;
    return 2;
  } catch (...) {
    // bind() failing (Register refused, server gone) ends here.
    std::cerr << "cast: " << contract.componentId << ": " << describe(std::current_exception()) << std::endl;
    component->close();
    return 1;
  }
}

}  // namespace cast
