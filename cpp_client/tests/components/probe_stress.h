// cast_probe's `stress` command, in a file of its own: the public API of one
// component called from many threads at once, against a real server.
#pragma once

#include <string>

#include "cast/cast.h"

namespace cast::probe {

// `threads` threads each add, read, overwrite (versioned), lock and unlock
// `perThread` entries of their own at once, while one watch counts the
// changes. Returns the command's JSON result: {"errors", "first_error",
// "changes", "duplicates"}.
std::string stress(Component& component, int threads, int perThread);

}  // namespace cast::probe
