#include "cast/types.h"

namespace cast {

const char* toString(Operation op) {
  switch (op) {
    case Operation::Add: return "ADD";
    case Operation::Overwrite: return "OVERWRITE";
    case Operation::Delete: return "DELETE";
  }
  return "UNSPECIFIED";
}

const char* toString(LockMode mode) {
  switch (mode) {
    case LockMode::O: return "O";
    case LockMode::OD: return "OD";
    case LockMode::ODR: return "ODR";
  }
  return "UNSPECIFIED";
}

const char* toString(TaskState state) {
  switch (state) {
    case TaskState::Unspecified: return "UNSPECIFIED";
    case TaskState::Waiting: return "WAITING";
    case TaskState::Adopted: return "ADOPTED";
    case TaskState::Rejected: return "REJECTED";
    case TaskState::Retracted: return "RETRACTED";
    case TaskState::Completed: return "COMPLETED";
  }
  return "UNSPECIFIED";
}

const char* toString(TaskOutcome outcome) {
  switch (outcome) {
    case TaskOutcome::Unspecified: return "UNSPECIFIED";
    case TaskOutcome::Succeeded: return "SUCCEEDED";
    case TaskOutcome::Failed: return "FAILED";
    case TaskOutcome::Abandoned: return "ABANDONED";
  }
  return "UNSPECIFIED";
}

const char* toString(Delivery delivery) {
  switch (delivery) {
    case Delivery::Queue: return "queue";
    case Delivery::Latest: return "latest";
  }
  return "unspecified";
}

const char* toString(Priority priority) {
  switch (priority) {
    case Priority::High: return "high";
    case Priority::Medium: return "medium";
    case Priority::Low: return "low";
  }
  return "unspecified";
}

std::ostream& operator<<(std::ostream& os, const WorkingMemoryChange& c) {
  os << "WorkingMemoryChange(" << c.operation() << " " << c.subarchitecture() << "/" << c.id() << " type=" << c.type()
     << " v=" << c.version() << " rev=" << c.revision() << " by=" << c.sourceComponent();
  if (c.skipped() > 0) os << " skipped=" << c.skipped() << " from rev=" << c.firstSkippedRevision();
  return os << ")";
}

std::ostream& operator<<(std::ostream& os, const Task& t) {
  return os << "Task(" << t.taskId() << " '" << t.name() << "' " << t.state() << ")";
}

}  // namespace cast
