// The library's release and wire API (cast/version.h), both taken from what the
// library is built from: CAST_LIBRARY_VERSION is the VERSION file (CMake
// defines it for this file), the package from the generated cast.v1 code.
#include "cast/version.h"

#include "cast/v1/directory.pb.h"

namespace cast {

const char* libraryVersion() { return CAST_LIBRARY_VERSION; }

std::string wireApi() { return v1::RegisterRequest::descriptor()->file()->package(); }

}  // namespace cast
