// A small JSON reader that keeps the order of object members, which
// google::protobuf::Struct does not: cast::connect needs "the first server"
// of system.json as `cast run` wrote it.
#pragma once

#include <string>
#include <utility>
#include <vector>

namespace cast::detail {

// One parsed JSON value.
struct JsonValue {
  enum class Kind { Null, Bool, Number, String, Array, Object };
  Kind kind = Kind::Null;
  bool boolean = false;
  double number = 0;
  std::string string;
  std::vector<JsonValue> items;                             // an array's elements
  std::vector<std::pair<std::string, JsonValue>> members;   // an object's members, in order

  // The member `key` of an object; nullptr if absent or not an object.
  const JsonValue* find(const std::string& key) const;
  bool isString() const { return kind == Kind::String; }
  bool isObject() const { return kind == Kind::Object; }
};

// Parses `text`; throws std::invalid_argument saying where it is not JSON.
JsonValue parseJson(const std::string& text);

}  // namespace cast::detail
