// The value types of the component API: addresses, write results, entries,
// change events and tasks. They are plain copies: nothing here refers back to
// the working memory, so a component may keep, change or pass them around
// freely without affecting what other components read.
#pragma once

#include <google/protobuf/message.h>

#include <cstdint>
#include <memory>
#include <optional>
#include <climits>
#include <ostream>
#include <string>
#include <string_view>
#include <type_traits>
#include <vector>

#include "cast/errors.h"

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

// The full protobuf name of a message type, as entry types are named.
template <class T>
const std::string& typeName() {
  static_assert(std::is_base_of_v<google::protobuf::Message, T>,
                "entry types are protobuf messages: generate them with cast_add_entry_types()");
  return T::descriptor()->full_name();
}

class ValueView;

namespace detail {

// A value's bytes that the server lent by shared memory (on its host): they
// are in a segment of its memory mapped read-only, and stay as they are
// while this object lives; the value is given back when it goes (the
// transport's Lease, shm_session.cc).
class LentBytes {
 public:
  virtual ~LentBytes() = default;
  const char* data() const { return data_; }
  std::size_t size() const { return size_; }

 protected:
  LentBytes(const char* data, std::size_t size) : data_(data), size_(size) {}

 private:
  const char* data_;
  std::size_t size_;
};

// An entry as the transport returns it: the value still serialised, either
// in `data` or, lent by shared memory, in `lent` (`data` then empty).
struct EntryRecord {
  WorkingMemoryAddress address;
  std::string type;
  std::string data;
  std::uint64_t version = 0;
  std::string author;
  std::uint64_t revision = 0;
  std::int64_t modifiedNs = 0;
  std::shared_ptr<const LentBytes> lent;

  // The serialised value, wherever it is; valid while this record lives.
  std::string_view bytes() const {
    return lent ? std::string_view(lent->data(), lent->size()) : std::string_view(data);
  }
};

// A change event as the transport returns it.
struct EventRecord {
  std::uint64_t revision = 0;
  Operation operation = Operation::Add;
  WorkingMemoryAddress address;
  std::string type;
  std::string sourceComponent;
  std::string sourceSubarchitecture;
  std::uint64_t version = 0;
  std::int64_t timeNs = 0;
  std::optional<EntryRecord> entry;
  // What a Latest watch did not receive because this change replaced it.
  std::uint64_t skipped = 0;
  std::uint64_t firstSkippedRevision = 0;
};

// Parses `data` as T after checking the declared type. `what` names the thing
// read in errors ("entry 'x'"), `sa` the subarchitecture it is in (both
// errors name it, as Python's do: "entry 'x' in subarchitecture 'vision' has
// type ..."), and `why` says how bytes that do not parse got there and what
// to do about them. Stored bytes that do not parse are an
// InvalidArgumentError like a wrong type, never a bare protobuf failure, so
// callers handle one kind of error.
template <class T>
T decode(const std::string& declaredType, std::string_view data, const std::string& what, const std::string& sa,
         const std::string& why) {
  const std::string& expected = typeName<T>();
  const std::string where = what + " in subarchitecture '" + sa + "'";
  if (declaredType != expected) {
    throw InvalidArgumentError(where + " has type " + declaredType + ", not " + expected +
                               ": read it with the right class");
  }
  T value;
  if (data.size() > static_cast<std::size_t>(INT_MAX) ||
      !value.ParseFromArray(data.data(), static_cast<int>(data.size()))) {
    throw InvalidArgumentError(where + " does not parse as " + expected + " (" + std::to_string(data.size()) +
                               " stored bytes): " + why);
  }
  return value;
}

// The value of an entry as T (see decode).
template <class T>
T decodeEntry(const EntryRecord& r) {
  return decode<T>(r.type, r.bytes(), "entry '" + r.address.id + "'", r.address.subarchitecture,
                   "it was written corrupt or with another schema; overwrite or delete it");
}

}  // namespace detail

// An entry read from a WM: a fresh copy of its value and its metadata.
template <class T>
struct Entry {
  WorkingMemoryAddress address;
  std::string type;
  T value;
  std::uint64_t version = 0;
  std::string author;        // component that made the last write
  std::uint64_t revision = 0;  // WM revision of the last write
  std::int64_t modifiedNs = 0;  // server time of the last write (ns since the epoch)

  const std::string& id() const { return address.id; }
};

namespace detail {
template <class T>
Entry<T> toEntry(const EntryRecord& r) {
  return Entry<T>{r.address, r.type, decodeEntry<T>(r), r.version, r.author, r.revision, r.modifiedNs};
}
}  // namespace detail

// One change event as delivered to an onChange callback. Copies share the
// event (and its entry's bytes), so passing a change around is cheap.
class WorkingMemoryChange {
 public:
  explicit WorkingMemoryChange(detail::EventRecord event)
      : WorkingMemoryChange(std::make_shared<const detail::EventRecord>(std::move(event))) {}
  // The event with what a Latest watch skipped before it (on the server and
  // in the component's own queue, added up).
  WorkingMemoryChange(std::shared_ptr<const detail::EventRecord> event, std::uint64_t skipped,
                      std::uint64_t firstSkippedRevision)
      : ev_(std::move(event)), skipped_(skipped), firstSkipped_(firstSkippedRevision) {}
  explicit WorkingMemoryChange(std::shared_ptr<const detail::EventRecord> event)
      : WorkingMemoryChange(event, event->skipped, event->firstSkippedRevision) {}

  Operation operation() const { return ev_->operation; }
  std::uint64_t revision() const { return ev_->revision; }
  const std::string& type() const { return ev_->type; }
  std::uint64_t version() const { return ev_->version; }
  const std::string& sourceComponent() const { return ev_->sourceComponent; }
  const std::string& sourceSubarchitecture() const { return ev_->sourceSubarchitecture; }
  std::int64_t timeNs() const { return ev_->timeNs; }
  const WorkingMemoryAddress& address() const { return ev_->address; }
  const std::string& id() const { return ev_->address.id; }
  const std::string& subarchitecture() const { return ev_->address.subarchitecture; }
  // With Delivery::Latest: how many earlier changes of this entry the watch
  // did not receive because this one replaced them (0: none), and the
  // revision of the oldest of them (0: none); the skipped ones lie between
  // it and revision(). Always 0 with Delivery::Queue.
  std::uint64_t skipped() const { return skipped_; }
  std::uint64_t firstSkippedRevision() const { return firstSkipped_; }
  // Whether the event carries the entry (a matching filter set includeEntry).
  bool hasEntry() const { return ev_->entry.has_value(); }
  // The entry carried by the event (after the write; for DELETE, as it was).
  template <class T>
  Entry<T> entry() const {
    if (!ev_->entry) throw InvalidArgumentError("this change carries no entry: ask for it with includeEntry");
    return detail::toEntry<T>(*ev_->entry);
  }
  // The value the event carries, serialised, not copied (cast/views.h): on
  // the server's host a large value is the server's shared memory, held
  // while the view (or this change) lives. InvalidArgumentError when the
  // change carries no entry.
  ValueView view() const;

 private:
  std::shared_ptr<const detail::EventRecord> ev_;
  std::uint64_t skipped_ = 0;
  std::uint64_t firstSkipped_ = 0;
};

std::ostream& operator<<(std::ostream& os, const WorkingMemoryChange& change);

namespace detail {
// A task as the transport returns it.
struct TaskRecord {
  std::string taskId;
  std::string name;
  std::string subarchitecture;
  std::string component;
  std::int32_t priority = 0;
  TaskState state = TaskState::Unspecified;
  TaskOutcome outcome = TaskOutcome::Unspecified;
  std::string reason;
  std::string dataType;  // full name of the payload's type, empty if none
  std::string data;      // serialised payload
};
}  // namespace detail

// A task proposed by a managed component, as its task manager decided.
class Task {
 public:
  Task() = default;
  explicit Task(detail::TaskRecord record) : rec_(std::move(record)) {}

  const std::string& taskId() const { return rec_.taskId; }
  const std::string& name() const { return rec_.name; }
  const std::string& subarchitecture() const { return rec_.subarchitecture; }  // SA whose TM decided
  const std::string& component() const { return rec_.component; }              // the proposer
  std::int32_t priority() const { return rec_.priority; }
  TaskState state() const { return rec_.state; }
  TaskOutcome outcome() const { return rec_.outcome; }
  const std::string& reason() const { return rec_.reason; }  // why rejected, retracted or ended
  // Whether the proposal carried a payload.
  bool hasData() const { return !rec_.dataType.empty(); }
  // The proposal's payload as T (nullopt if none was given).
  template <class T>
  std::optional<T> data() const {
    if (rec_.dataType.empty()) return std::nullopt;
    return detail::decode<T>(rec_.dataType, rec_.data, "task '" + rec_.taskId + "' data", rec_.subarchitecture,
                             "it was proposed corrupt or with another schema; complete or retract the task");
  }

 private:
  detail::TaskRecord rec_;
};

std::ostream& operator<<(std::ostream& os, const Task& task);

}  // namespace cast
