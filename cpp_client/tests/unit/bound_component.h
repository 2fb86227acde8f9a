// A component bound to the in-memory transport, and the test value most unit
// tests write: what component_test.cc and lock_guard_test.cc share.
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "cast/component.h"
#include "cast_testing.pb.h"
#include "fake_transport.h"

namespace cast::testing {

// An unmanaged component bound to a FakeTransport of its own, closed at the end of the scope.
struct Bound {
  explicit Bound(const std::string& id = "comp", const std::string& sa = "vision") {
    transport = std::make_shared<FakeTransport>(cast::Identity{id, sa, false});
    component.bind(transport);
  }
  ~Bound() { component.close(); }
  std::shared_ptr<FakeTransport> transport;
  cast::UnmanagedComponent component;
};

inline Counter counter(const std::string& writer, std::int64_t value) {
  Counter c;
  c.set_writer(writer);
  c.set_value(value);
  return c;
}

}  // namespace cast::testing
