// The plain values the rest of the API is built from: what a write did, lock
// modes, component and task states, delivery and dispatch priorities, an
// entry's address, a write's result, a component's identity and the name of
// an entry type. cast/types.h adds what a component reads (entries, change
// events, tasks) on top of them.
#pragma once

#include <google/protobuf/message.h>

#include <cstdint>
#include <ostream>
#include <string>
#include <type_traits>

namespace cast {

// What a write did. Values equal cast.v1.Operation.
enum class Operation { Add = 1, Overwrite = 2, Delete = 3 };

// What a lock keeps other components from doing. Values equal cast.v1.LockMode.
enum class LockMode {
  O = 1,    // others may not overwrite
  OD = 2,   // nor delete
  ODR = 3,  // nor read
};

// A component's life stage as its session reports it (cast.v1.ComponentState).
// Started: start() returned and its watches are registered; run() waits for
// the system's start barrier (a component `cast run` launched).
enum class ComponentState { Starting = 2, Running = 3, Stopping = 4, Started = 6 };

// Where a task is in its life (cast.v1.TaskState).
enum class TaskState { Unspecified = 0, Waiting = 1, Adopted = 2, Rejected = 3, Retracted = 4, Completed = 5 };

// What the proposer reports when a task ends (cast.v1.TaskOutcome).
enum class TaskOutcome { Unspecified = 0, Succeeded = 1, Failed = 2, Abandoned = 3 };

// What a watch receives when it falls behind the writers (cast.v1.Delivery):
// Queue, every change in order; Latest, only the newest change of each entry
// it has not taken yet, with WorkingMemoryChange::skipped() saying how many it
// replaced (for fast data such as images read by slower consumers).
enum class Delivery { Queue = 0, Latest = 1 };

// Which of a component's pending callbacks its dispatcher runs first: the
// highest priority, first in first out within one.
enum class Priority { High = 0, Medium = 1, Low = 2 };

// How onChange delivers a watch's changes (the last parameter of onChange).
struct WatchOptions {
  Delivery delivery = Delivery::Queue;
  Priority priority = Priority::Medium;
};

const char* toString(Operation op);
const char* toString(LockMode mode);
const char* toString(TaskState state);
const char* toString(TaskOutcome outcome);
const char* toString(Delivery delivery);
const char* toString(Priority priority);
inline std::ostream& operator<<(std::ostream& os, Operation op) { return os << toString(op); }
inline std::ostream& operator<<(std::ostream& os, LockMode m) { return os << toString(m); }
inline std::ostream& operator<<(std::ostream& os, TaskState s) { return os << toString(s); }
inline std::ostream& operator<<(std::ostream& os, TaskOutcome o) { return os << toString(o); }
inline std::ostream& operator<<(std::ostream& os, Delivery d) { return os << toString(d); }
inline std::ostream& operator<<(std::ostream& os, Priority p) { return os << toString(p); }

// Where an entry lives: its id in the WM of one subarchitecture.
struct WorkingMemoryAddress {
  std::string id;
  std::string subarchitecture;
  bool operator==(const WorkingMemoryAddress& o) const { return id == o.id && subarchitecture == o.subarchitecture; }
  bool operator!=(const WorkingMemoryAddress& o) const { return !(*this == o); }
};

// The result of one write: the WM revision it made and the entry's version.
struct WriteResult {
  std::uint64_t revision = 0;
  std::uint64_t version = 0;
};

// Who a component is: its id, its SA, and whether it may write every SA.
struct Identity {
  std::string componentId;
  std::string subarchitecture;
  bool privileged = false;
};

// The full protobuf name of a message type, as entry types are named.
template <class T>
const std::string& typeName() {
  static_assert(std::is_base_of_v<google::protobuf::Message, T>,
                "entry types are protobuf messages: generate them with cast_add_entry_types()");
  return T::descriptor()->full_name();
}

}  // namespace cast
