// The values a component reads: entries, change events and tasks (Python:
// cast/client/types.py; Java: Entry, WorkingMemoryChange, Task), on top of
// the plain values of cast/basic_types.h. They are plain copies: nothing here
// refers back to the working memory, so a component may keep, change or pass
// them around freely without affecting what other components read.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <ostream>
#include <string>

#include "cast/basic_types.h"
#include "cast/detail/records.h"
#include "cast/errors.h"

namespace cast {

class ValueView;

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
