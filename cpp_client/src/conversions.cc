// Wire messages <-> library types (conversions.h). Enums are cast by value:
// the library's enums are declared with the proto's numbers (types.h).
#include "conversions.h"

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

EntryRecord entryFromPb(const v1::Entry& e) {
  EntryRecord r;
  r.address = WorkingMemoryAddress{e.address().id(), e.address().subarchitecture()};
  r.type = e.type();
  r.data = e.value().value();
  r.version = e.version();
  r.author = e.author();
  r.revision = e.revision();
  r.modifiedNs = nanos(e.modified());
  return r;
}

EventRecord eventFromPb(const v1::ChangeEvent& e) {
  EventRecord r;
  r.revision = e.revision();
  r.operation = static_cast<Operation>(e.operation());
  r.address = WorkingMemoryAddress{e.address().id(), e.address().subarchitecture()};
  r.type = e.type();
  r.sourceComponent = e.source_component();
  r.sourceSubarchitecture = e.source_subarchitecture();
  r.version = e.version();
  r.timeNs = nanos(e.time());
  if (e.has_entry()) r.entry = entryFromPb(e.entry());
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

}  // namespace cast::detail
