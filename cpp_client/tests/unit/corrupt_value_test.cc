// A stored value whose bytes do not parse as its declared type (written
// corrupt, or with another schema) is an InvalidArgumentError naming the
// entry's id, SA and type, wherever the library decodes one: get, getEntry,
// getAll, the entry of a change event, the data of a task.
#include <gtest/gtest.h>

#include <functional>
#include <future>

#include "cast/component.h"
#include "cast_testing.pb.h"
#include "fake_transport.h"

namespace {

using namespace std::chrono_literals;
using cast::testing::Counter;
using cast::testing::FakeTransport;

// Field 1 (writer, a string) said to be 5 bytes long, with 2 left: no Counter.
const std::string kCorrupt("\x0a\x05" "ab", 4);
const char* const kExpected =
    "entry 'bad' in subarchitecture 'vision' does not parse as cast.testing.Counter (4 stored bytes): it was "
    "written corrupt or with another schema; overwrite or delete it";

std::string messageOf(const std::function<void()>& fn) {
  try {
    fn();
  } catch (const cast::InvalidArgumentError& e) {
    return e.message();
  }
  return "(no InvalidArgumentError)";
}

struct Stored {
  Stored() {
    transport = std::make_shared<FakeTransport>(cast::Identity{"reader", "vision", false});
    component.bind(transport);
    // Straight through the transport: the component API always writes valid values.
    transport->add("vision", "bad", cast::typeName<Counter>(), kCorrupt);
  }
  ~Stored() { component.close(); }
  std::shared_ptr<FakeTransport> transport;
  cast::UnmanagedComponent component;
};

TEST(CorruptValue, GetGetEntryAndGetAllSayWhichEntry) {
  Stored s;
  EXPECT_EQ(messageOf([&] { s.component.get<Counter>("bad"); }), kExpected);
  EXPECT_EQ(messageOf([&] { s.component.getEntry<Counter>("bad"); }), kExpected);
  EXPECT_EQ(messageOf([&] { s.component.getAll<Counter>(); }), kExpected);
}

TEST(CorruptValue, TheEntryOfAChangeEventSaysWhichEntry) {
  auto transport = std::make_shared<FakeTransport>(cast::Identity{"reader", "vision", false});
  cast::UnmanagedComponent component;
  component.bind(transport);
  std::promise<std::string> seen;
  auto watch = component.onChange(cast::localTypeFilter<Counter>().withEntry(),
                                  [&](const cast::WorkingMemoryChange& change) {
                                    EXPECT_TRUE(change.hasEntry());
                                    seen.set_value(messageOf([&] { change.entry<Counter>(); }));
                                  });
  transport->add("vision", "bad", cast::typeName<Counter>(), kCorrupt);
  auto future = seen.get_future();
  ASSERT_EQ(future.wait_for(5s), std::future_status::ready);
  EXPECT_EQ(future.get(), kExpected);
  component.close();
}

// Hands the data of each adopted task to the test.
class Tasks : public cast::ManagedComponent {
 public:
  void taskAdopted(const cast::Task& task) override {
    messages.set_value(messageOf([&] { task.data<Counter>(); }));
  }
  std::promise<std::string> messages;
};

// What reading the data of a task proposed with `type` and `data` as a
// Counter says, in a component of vision.
std::string taskDataError(const std::string& type, const std::string& data) {
  auto transport = std::make_shared<FakeTransport>(cast::Identity{"worker", "vision", false});
  Tasks component;
  component.bind(transport);
  transport->propose("work", type, data, 0);
  auto future = component.messages.get_future();
  const bool adopted = future.wait_for(5s) == std::future_status::ready;
  component.close();
  return adopted ? future.get() : "(no task adopted within 5 s)";
}

TEST(CorruptValue, TheDataOfATaskSaysWhichTask) {
  EXPECT_EQ(taskDataError(cast::typeName<Counter>(), kCorrupt),
            "task 'task-1' data in subarchitecture 'vision' does not parse as cast.testing.Counter (4 stored bytes): "
            "it was proposed corrupt or with another schema; complete or retract the task");
}

TEST(CorruptValue, AWrongTypeIsStillNamedAsSuch) {
  Stored s;
  cast::testing::Pose pose;
  s.component.add("pose", pose);
  EXPECT_EQ(messageOf([&] { s.component.get<Counter>("pose"); }),
            "entry 'pose' in subarchitecture 'vision' has type cast.testing.Pose, not cast.testing.Counter: read it "
            "with the right class");
}

TEST(CorruptValue, TheDataOfATaskOfAnotherTypeSaysWhichTaskAndWhere) {
  EXPECT_EQ(taskDataError(cast::typeName<cast::testing::Pose>(), cast::testing::Pose().SerializeAsString()),
            "task 'task-1' data in subarchitecture 'vision' has type cast.testing.Pose, not cast.testing.Counter: "
            "read it with the right class");
}

}  // namespace
