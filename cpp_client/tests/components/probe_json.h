// A tiny JSON writer for the test components' stdout protocol (one JSON
// object per line). Message values are embedded as protobuf's own JSON.
#pragma once

#include <google/protobuf/message.h>
#include <google/protobuf/util/json_util.h>

#include <cstdint>
#include <sstream>
#include <string>
#include <vector>

namespace cast::probe {

inline std::string quote(const std::string& s) {
  std::string out = "\"";
  for (unsigned char c : s) {
    switch (c) {
      case '"': out += "\\\""; break;
      case '\\': out += "\\\\"; break;
      case '\n': out += "\\n"; break;
      case '\r': out += "\\r"; break;
      case '\t': out += "\\t"; break;
      default:
        if (c < 0x20) {
          char buf[8];
          std::snprintf(buf, sizeof buf, "\\u%04x", c);
          out += buf;
        } else {
          out += static_cast<char>(c);  // UTF-8 passes through
        }
    }
  }
  return out + "\"";
}

inline std::string messageJson(const google::protobuf::Message& m) {
  std::string out;
  google::protobuf::util::JsonPrintOptions options;
  options.preserve_proto_field_names = true;
  (void)google::protobuf::util::MessageToJsonString(m, &out, options);
  return out;
}

// Builds {"k": v, ...} in insertion order.
class Object {
 public:
  Object& str(const std::string& key, const std::string& value) { return raw(key, quote(value)); }
  Object& num(const std::string& key, std::int64_t value) { return raw(key, std::to_string(value)); }
  Object& unum(const std::string& key, std::uint64_t value) { return raw(key, std::to_string(value)); }
  Object& boolean(const std::string& key, bool value) { return raw(key, value ? "true" : "false"); }
  Object& message(const std::string& key, const google::protobuf::Message& m) { return raw(key, messageJson(m)); }
  Object& raw(const std::string& key, const std::string& json) {
    parts_.push_back(quote(key) + ": " + json);
    return *this;
  }
  std::string json() const {
    std::string out = "{";
    for (size_t i = 0; i < parts_.size(); ++i) out += (i ? ", " : "") + parts_[i];
    return out + "}";
  }

 private:
  std::vector<std::string> parts_;
};

inline std::string array(const std::vector<std::string>& items) {
  std::string out = "[";
  for (size_t i = 0; i < items.size(); ++i) out += (i ? ", " : "") + items[i];
  return out + "]";
}

}  // namespace cast::probe
