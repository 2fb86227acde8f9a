// The process environment as a map, so that what reads it (the launch
// contract, cast::connect) can be tested with an environment of its own.
#pragma once

#include <map>
#include <string>

namespace cast::detail {

// Every NAME=value of the process environment (defined in runner.cc).
std::map<std::string, std::string> processEnv();

}  // namespace cast::detail
