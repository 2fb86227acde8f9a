// Wire messages <-> library types (conversions.h). Enums are cast by value:
// the library's enums are declared with the proto's numbers (types.h).
#include "conversions.h"

#include <algorithm>
#include <limits>

#include "shm_session.h"

namespace cast::detail {

namespace {
constexpr char kTypeUrlPrefix[] = "type.googleapis.com/";
}  // namespace

v1::EntryAddress addressPb(const std::string& sa, const std::string& id) {
  v1::EntryAddress a;
  a.set_id(id);
  a.set_subarchitecture(sa);
  return a;
}

void setAny(google::protobuf::Any* any, const std::string& type, const std::string& data) {
  any->set_type_url(kTypeUrlPrefix + type);
  any->set_value(data);
}

std::string typeFromUrl(const std::string& url) {
  const auto slash = url.rfind('/');
  return slash == std::string::npos ? url : url.substr(slash + 1);
}

std::int64_t nanos(const google::protobuf::Timestamp& t) {
  return static_cast<std::int64_t>(t.seconds()) * 1000000000LL + t.nanos();
}

EntryRecord entryFromPb(const v1::Entry& e, ReadCall* call) {
  EntryRecord r;
  r.address = WorkingMemoryAddress{e.address().id(), e.address().subarchitecture()};
  r.type = e.type();
  if (e.has_shared_value()) {
    if (call == nullptr) {
      throw UnavailableError("entry '" + e.address().id() +
                             "' came by shared memory on a call that named no session: read it again");
    }
    r.lent = call->claim(e.shared_value());
  } else {
    r.data = e.value().value();
  }
  r.version = e.version();
  r.author = e.author();
  r.revision = e.revision();
  r.modifiedNs = nanos(e.modified());
  return r;
}

EventRecord eventFromPb(const v1::ChangeEvent& e, ReadCall* call) {
  EventRecord r;
  r.revision = e.revision();
  r.operation = static_cast<Operation>(e.operation());
  r.address = WorkingMemoryAddress{e.address().id(), e.address().subarchitecture()};
  r.type = e.type();
  r.sourceComponent = e.source_component();
  r.sourceSubarchitecture = e.source_subarchitecture();
  r.version = e.version();
  r.timeNs = nanos(e.time());
  if (e.has_entry()) r.entry = entryFromPb(e.entry(), call);
  r.skipped = e.skipped();
  r.firstSkippedRevision = e.first_skipped_revision();
  return r;
}

TaskRecord taskFromPb(const v1::Task& t) {
  TaskRecord r;
  r.taskId = t.task_id();
  r.name = t.name();
  r.subarchitecture = t.subarchitecture();
  r.component = t.component();
  r.priority = t.priority();
  r.state = static_cast<TaskState>(t.state());
  r.outcome = static_cast<TaskOutcome>(t.outcome());
  r.reason = t.reason();
  if (t.has_data() && !t.data().type_url().empty()) {
    r.dataType = typeFromUrl(t.data().type_url());
    r.data = t.data().value();
  }
  return r;
}

void filterToPb(const ChangeFilter& f, v1::ChangeFilter* pb) {
  for (Operation op : f.operations) pb->add_operations(static_cast<v1::Operation>(op));
  pb->set_type(f.type);
  pb->set_id(f.id);
  pb->set_subarchitecture(f.subarchitecture);
  pb->set_source_component(f.sourceComponent);
  pb->set_source_subarchitecture(f.sourceSubarchitecture);
  pb->set_include_entry(f.includeEntry);
}

WriteResult writeResult(const v1::WriteResponse& r) { return WriteResult{r.revision(), r.version()}; }

v1::WriteRequest addRequest(const std::string& sa, const std::string& id, const std::string& type,
                            const std::string& data) {
  v1::WriteRequest request;
  auto* add = request.mutable_add();
  *add->mutable_address() = addressPb(sa, id);
  setAny(add->mutable_value(), type, data);
  return request;
}

v1::WriteRequest overwriteRequest(const std::string& sa, const std::string& id, const std::string& type,
                                  const std::string& data, std::optional<std::uint64_t> expectedVersion) {
  v1::WriteRequest request;
  auto* overwrite = request.mutable_overwrite();
  *overwrite->mutable_address() = addressPb(sa, id);
  setAny(overwrite->mutable_value(), type, data);
  if (expectedVersion) overwrite->set_expected_version(*expectedVersion);
  return request;
}

v1::WriteRequest deleteRequest(const std::string& sa, const std::string& id,
                               std::optional<std::uint64_t> expectedVersion) {
  v1::WriteRequest request;
  auto* del = request.mutable_delete_();
  *del->mutable_address() = addressPb(sa, id);
  if (expectedVersion) del->set_expected_version(*expectedVersion);
  return request;
}

v1::WriteRequest batchRequest(const std::vector<BatchOp>& ops) {
  v1::WriteRequest request;
  auto* batch = request.mutable_batch();
  for (const auto& op : ops) {
    auto* item = batch->add_operations();
    if (op.operation == Operation::Add) {
      auto* add = item->mutable_add();
      *add->mutable_address() = addressPb(op.subarchitecture, op.id);
      setAny(add->mutable_value(), op.type, op.data);
    } else if (op.operation == Operation::Overwrite) {
      auto* overwrite = item->mutable_overwrite();
      *overwrite->mutable_address() = addressPb(op.subarchitecture, op.id);
      setAny(overwrite->mutable_value(), op.type, op.data);
      if (op.expectedVersion) overwrite->set_expected_version(*op.expectedVersion);
    } else {
      auto* del = item->mutable_delete_();
      *del->mutable_address() = addressPb(op.subarchitecture, op.id);
      if (op.expectedVersion) del->set_expected_version(*op.expectedVersion);
    }
  }
  return request;
}

v1::WriteRequest lockRequest(const std::string& sa, const std::string& id, LockMode mode, bool noWait,
                             std::optional<std::chrono::milliseconds> timeout) {
  v1::WriteRequest request;
  auto* lock = request.mutable_lock();
  *lock->mutable_address() = addressPb(sa, id);
  lock->set_mode(static_cast<v1::LockMode>(mode));
  lock->set_no_wait(noWait);
  if (timeout && !noWait) {
    // 0 on the wire means "no bound": a timeout of 0 ms is the shortest bound
    // instead, and one past the field's range (49 days) is as good as none.
    const std::int64_t ms = std::max<std::int64_t>(1, timeout->count());
    if (ms <= std::numeric_limits<std::uint32_t>::max()) request.set_timeout_ms(static_cast<std::uint32_t>(ms));
  }
  return request;
}

v1::WriteRequest unlockRequest(const std::string& sa, const std::string& id) {
  v1::WriteRequest request;
  *request.mutable_unlock()->mutable_address() = addressPb(sa, id);
  return request;
}

}  // namespace cast::detail
