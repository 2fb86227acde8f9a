// A socket a component's dispatcher thread reads itself: a shared-memory
// session that carries a watch's events (docs/client-protocol.md, "A watch's
// events on the session's socket"). Read on the thread that runs the
// callbacks, an event's callback runs on the thread the kernel woke for its
// frame, with no hand-off between threads (the Python client's
// dispatcher.Source, the Java client's Dispatcher.Source).
#pragma once

#include <functional>
#include <memory>

namespace cast::detail {

class EventSource {
 public:
  virtual ~EventSource() = default;
  // Its descriptor, to wait on for something to read; -1 once it ended (the
  // dispatcher then forgets it).
  virtual int sourceFd() const = 0;
  // Reads what is there without waiting and handles each frame on this
  // thread; false, reading nothing, when another thread reads it now (it
  // handles what comes).
  virtual bool pump() = 0;
};

// Hands a source to the dispatcher that reads it from then on, held weakly:
// the source goes when its last owner lets it go.
using AttachSource = std::function<void(std::weak_ptr<EventSource>)>;

}  // namespace cast::detail
