// A launched component's first contact with its server (docs/client-protocol.md,
// "Start-up", step 2): the system was started first, so a server that does not
// answer at once is busy or still starting, and the first call is asked again
// with backoff for the connect window (cast::kConnectWindow, 20 s) before the
// runner gives up. The twin of LaunchContract.connect in
// python/cast/client/runner.py and of ConnectWindow.java: the same codes, the
// same words.
#pragma once

#include <chrono>
#include <functional>
#include <sstream>
#include <string>

#include "backoff.h"
#include "cast/errors.h"
#include "cast/log.h"

namespace cast::detail {

// Whether a failed first contact is asked again: the server is down, still
// starting (UNAVAILABLE) or too busy to answer in time (DEADLINE_EXCEEDED).
// Any other failure (a refused token, a bad TLS file) is the launch
// environment's fault, and asking again would not mend it.
inline bool connectRetried(const std::string& code) { return code == "UNAVAILABLE" || code == "DEADLINE_EXCEEDED"; }

// What the runner says when nothing answered within `window`: where it asked,
// for how long, what to check, and the last error.
inline std::string connectGaveUp(const std::string& endpoint, Millis window, bool tls, const std::string& lastError) {
  std::ostringstream seconds;
  seconds << static_cast<double>(window.count()) / 1000.0;  // 20000 ms -> "20", as Python's {:g}
  return "no CAST system answered at " + endpoint + " within " + seconds.str() + " s (CAST_ENDPOINT, spoken to " +
         (tls ? "with TLS" : "in plaintext") +
         "): check that the system is running and that CAST_ENDPOINT and CAST_TLS_* are its address and TLS "
         "settings (last error: " +
         lastError + ")";
}

// The time and the waits of the window, so that tests can run it on a clock of
// their own.
struct ConnectClock {
  std::function<std::chrono::steady_clock::time_point()> now = [] { return std::chrono::steady_clock::now(); };
  // Waits up to the given time; true when the component was asked to stop
  // meanwhile (the runner's signal handler), which ends the asking.
  std::function<bool(Millis)> wait;
};

// Calls `attempt` (the first call to the server) until it returns. A failure
// connectRetried() accepts is logged and asked again after a backoff until
// `window` has passed since the first try, then UnavailableError with
// connectGaveUp(); any other error is thrown at once. Asked to stop while
// waiting: CastError with code CANCELLED.
template <class T>
T connectWithin(const std::string& endpoint, bool tls, Millis window, const std::function<T()>& attempt,
                const ConnectClock& clock, const Logger& log) {
  const auto deadline = clock.now() + window;
  Backoff backoff;
  while (true) {
    try {
      return attempt();
    } catch (const CastError& e) {
      if (!connectRetried(e.code())) throw;
      if (clock.now() >= deadline) throw UnavailableError(connectGaveUp(endpoint, window, tls, e.message()));
      log.info("the server at " + endpoint + " is not answering yet (" + e.message() + "); asking again");
    }
    if (clock.wait(backoff.next())) {
      throw CastError("asked to stop while waiting for the server at " + endpoint + " to answer", "CANCELLED");
    }
  }
}

}  // namespace cast::detail
