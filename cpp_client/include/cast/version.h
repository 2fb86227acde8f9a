// The release and the wire API of the CAST C++ client library.
#pragma once

#include <string>

namespace cast {

/// The release of the library linked in ("0.1.0": the repository's VERSION file, which CMake
/// reads). The library sends it in its session registration, and `cast components` shows it.
const char* libraryVersion();

/// The wire API the library speaks: the protobuf package of its generated code ("cast.v1").
std::string wireApi();

}  // namespace cast
