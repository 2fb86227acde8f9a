// Internal: not part of the API. What the transport hands the component
// layer: entries, change events and tasks with their values still
// serialised, and the decoding the public templates of cast/types.h and
// cast/views.h (Entry<T>, WorkingMemoryChange::entry<T>, Task::data<T>,
// ValueView::decode<T>) instantiate in the user's code, which is why this
// header is installed. Names here may change in any release.
#pragma once

#include <climits>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

#include "cast/basic_types.h"
#include "cast/errors.h"

namespace cast {

template <class T>
struct Entry;

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

// The entry as Entry<T> (complete where it is called: cast/types.h).
template <class T>
Entry<T> toEntry(const EntryRecord& r) {
  return Entry<T>{r.address, r.type, decodeEntry<T>(r), r.version, r.author, r.revision, r.modifiedNs};
}

}  // namespace detail
}  // namespace cast
