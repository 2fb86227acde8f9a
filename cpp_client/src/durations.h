// A duration as error messages show it ("3 s", "0.25 s"), shared by the
// Write stream's two transports (write_stream.cc, socket_writes.cc).
#pragma once

#include <chrono>
#include <string>

namespace cast::detail {

inline std::string secondsText(std::chrono::milliseconds ms) {
  std::string out = std::to_string(static_cast<double>(ms.count()) / 1000.0);
  out.erase(out.find_last_not_of('0') + 1);  // 3.000000 -> 3.
  if (!out.empty() && out.back() == '.') out.pop_back();
  return out + " s";
}

}  // namespace cast::detail
