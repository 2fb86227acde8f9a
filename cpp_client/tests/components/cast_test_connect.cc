// cast_test_connect: a plain program (no component, no runner) that uses a
// working memory through cast::connect, for tests/interop/test_connect.py.
// It finds the system as any script would (environment, runtime directory),
// watches the entry ID, adds it, reads it back, waits for its change, and
// prints one JSON line:
//
//   {"component": ..., "subarchitecture": ..., "privileged": ..., "version": ..., "event": "ADD", "writer": ...}
//
// Exit 0 on success; 1 with {"error": name, "message": ...} on a CastError.
//
//   cast_test_connect ID
#include <chrono>
#include <future>
#include <iostream>

#include "cast/cast.h"
#include "cast_testing.pb.h"
#include "probe_json.h"

int main(int argc, char** argv) {
  using cast::probe::Object;
  if (argc != 2) {
    std::cerr << "usage: " << argv[0] << " ENTRY_ID" << std::endl;
    return 2;
  }
  const std::string id = argv[1];
  try {
    auto wm = cast::connect();
    std::promise<std::string> changed;
    auto watch = wm->onChange(cast::addressFilter(id, {cast::Operation::Add}),
                              [&](const cast::WorkingMemoryChange& change) {
                                changed.set_value(cast::toString(change.operation()));
                              });
    cast::testing::Counter counter;
    counter.set_writer(wm->componentId());
    counter.set_value(42);
    wm->add(id, counter);
    auto entry = wm->getEntry<cast::testing::Counter>(id);
    auto event = changed.get_future();
    if (event.wait_for(std::chrono::seconds(20)) != std::future_status::ready) {
      std::cout << Object().str("error", "Timeout").str("message", "no change event within 20 s").json() << std::endl;
      return 1;
    }
    watch.cancel();
    std::cout << Object()
                     .str("component", wm->componentId())
                     .str("subarchitecture", wm->subarchitecture())
                     .boolean("privileged", wm->privileged())
                     .unum("version", entry.version)
                     .str("event", event.get())
                     .str("writer", entry.value.writer())
                     .json()
              << std::endl;
    wm->close();
    return 0;
  } catch (const cast::CastError& e) {
    std::cout << Object().str("error", e.name()).str("message", e.message()).json() << std::endl;
    return 1;
  }
}
