// Change filters and their helpers (docs/design.md section 5).
//
// A ChangeFilter says which change events a callback wants: every set field
// must match, an empty field matches anything, several filters given to one
// onChange are ORed. "Local" filters match the component's own
// subarchitecture; the SA is filled in when the filter is registered with
// onChange, so the helpers need no component.
#pragma once

#include <set>
#include <string>
#include <vector>

#include "cast/types.h"

namespace cast {

struct ChangeFilter {
  std::set<Operation> operations;  // empty: every operation
  std::string type;                // full message name, matched exactly
  std::string id;                  // entry id
  std::string subarchitecture;     // WM to watch; empty: every SA (unless local)
  std::string sourceComponent;     // id of the writing component
  std::string sourceSubarchitecture;  // SA of the writing component
  bool includeEntry = false;       // deliver the entry with each event
  bool local = false;              // the component's own SA (filled in by onChange)

  // The same filter, asking for the entry in each event.
  ChangeFilter withEntry() const;
  // The filter as sent: a local filter gets `ownSubarchitecture`.
  ChangeFilter resolve(const std::string& ownSubarchitecture) const;

  bool operator==(const ChangeFilter& o) const;
  bool operator!=(const ChangeFilter& o) const { return !(*this == o); }
};

std::ostream& operator<<(std::ostream& os, const ChangeFilter& filter);

using Operations = std::vector<Operation>;

// Changes to entries of the named type in the component's own SA.
ChangeFilter localTypeFilter(const std::string& typeName, const Operations& operations = {},
                             bool includeEntry = false);
// Changes to entries of type T in the component's own SA.
template <class T>
ChangeFilter localTypeFilter(const Operations& operations = {}, bool includeEntry = false) {
  return localTypeFilter(typeName<T>(), operations, includeEntry);
}

// Changes to entries of the named type in every SA.
ChangeFilter globalTypeFilter(const std::string& typeName, const Operations& operations = {},
                              bool includeEntry = false);
// Changes to entries of type T in every SA.
template <class T>
ChangeFilter globalTypeFilter(const Operations& operations = {}, bool includeEntry = false) {
  return globalTypeFilter(typeName<T>(), operations, includeEntry);
}

// Changes to one entry (in the own SA unless `subarchitecture` is given).
ChangeFilter addressFilter(const std::string& entryId, const Operations& operations = {},
                           const std::string& subarchitecture = "", bool includeEntry = false);
// Changes to one entry at `address`.
ChangeFilter addressFilter(const WorkingMemoryAddress& address, const Operations& operations = {},
                           bool includeEntry = false);

// Changes made by one component (in every SA unless `subarchitecture` is given).
ChangeFilter sourceFilter(const std::string& componentId, const Operations& operations = {},
                          const std::string& subarchitecture = "", bool includeEntry = false);

// Changes of the given operations (every SA, or only the own one if `local`).
ChangeFilter operationFilter(const Operations& operations, bool local = false, bool includeEntry = false);

}  // namespace cast
