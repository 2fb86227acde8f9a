#include "cast/filters.h"

#include <ostream>

namespace cast {

namespace {
// What every filter helper sets: the operations (none: every one) and
// whether the events carry the entry.
ChangeFilter filterOf(const Operations& operations, bool includeEntry) {
  ChangeFilter f;
  f.operations = std::set<Operation>(operations.begin(), operations.end());
  f.includeEntry = includeEntry;
  return f;
}
}  // namespace

ChangeFilter ChangeFilter::withEntry() const {
  ChangeFilter f = *this;
  f.includeEntry = true;
  return f;
}

ChangeFilter ChangeFilter::resolve(const std::string& ownSubarchitecture) const {
  ChangeFilter f = *this;
  if (f.local) {
    f.subarchitecture = ownSubarchitecture;
    f.local = false;
  }
  return f;
}

bool ChangeFilter::operator==(const ChangeFilter& o) const {
  return operations == o.operations && type == o.type && id == o.id && subarchitecture == o.subarchitecture &&
         sourceComponent == o.sourceComponent && sourceSubarchitecture == o.sourceSubarchitecture &&
         includeEntry == o.includeEntry && local == o.local;
}

std::ostream& operator<<(std::ostream& os, const ChangeFilter& f) {
  os << "ChangeFilter{";
  const char* sep = "";
  auto field = [&](const char* name, const std::string& value) {
    if (!value.empty()) {
      os << sep << name << "=" << value;
      sep = " ";
    }
  };
  if (!f.operations.empty()) {
    os << "operations=";
    const char* comma = "";
    for (Operation op : f.operations) {
      os << comma << op;
      comma = ",";
    }
    sep = " ";
  }
  field("type", f.type);
  field("id", f.id);
  field("subarchitecture", f.local ? std::string("<own>") : f.subarchitecture);
  field("source_component", f.sourceComponent);
  field("source_subarchitecture", f.sourceSubarchitecture);
  if (f.includeEntry) os << sep << "include_entry";
  return os << "}";
}

ChangeFilter localTypeFilter(const std::string& typeName, const Operations& operations, bool includeEntry) {
  ChangeFilter f = globalTypeFilter(typeName, operations, includeEntry);
  f.local = true;
  return f;
}

ChangeFilter globalTypeFilter(const std::string& typeName, const Operations& operations, bool includeEntry) {
  ChangeFilter f = filterOf(operations, includeEntry);
  f.type = typeName;
  return f;
}

ChangeFilter addressFilter(const std::string& entryId, const Operations& operations,
                           const std::string& subarchitecture, bool includeEntry) {
  ChangeFilter f = filterOf(operations, includeEntry);
  f.id = entryId;
  f.subarchitecture = subarchitecture;
  f.local = subarchitecture.empty();
  return f;
}

ChangeFilter addressFilter(const WorkingMemoryAddress& address, const Operations& operations, bool includeEntry) {
  return addressFilter(address.id, operations, address.subarchitecture, includeEntry);
}

ChangeFilter sourceFilter(const std::string& componentId, const Operations& operations,
                          const std::string& subarchitecture, bool includeEntry) {
  ChangeFilter f = filterOf(operations, includeEntry);
  f.sourceComponent = componentId;
  f.subarchitecture = subarchitecture;
  return f;
}

ChangeFilter operationFilter(const Operations& operations, bool local, bool includeEntry) {
  ChangeFilter f = filterOf(operations, includeEntry);
  f.local = local;
  return f;
}

}  // namespace cast
