// A component's arguments: the JSON object of CAST_ARGS (the `args:` of the
// component in the configuration), read through protobuf's JSON support into
// a google.protobuf.Struct, so no other JSON library is needed.
#pragma once

#include <google/protobuf/struct.pb.h>

#include <cstdint>
#include <string>
#include <vector>

namespace cast {

class Args {
 public:
  Args() = default;
  explicit Args(google::protobuf::Struct values) : values_(std::move(values)) {}

  // Parses a JSON object; InvalidArgumentError saying what is wrong otherwise.
  // An empty string is the empty object.
  static Args fromJson(const std::string& json);

  bool has(const std::string& key) const;
  // The value of `key`, or `fallback` if absent (or JSON null). A value of
  // another JSON type is an InvalidArgumentError naming the key, since a
  // silently ignored argument is a misconfiguration nobody notices.
  std::string getString(const std::string& key, const std::string& fallback = "") const;
  double getDouble(const std::string& key, double fallback = 0.0) const;
  // A number that must be integral (JSON has only doubles).
  std::int64_t getInt(const std::string& key, std::int64_t fallback = 0) const;
  bool getBool(const std::string& key, bool fallback = false) const;
  std::vector<std::string> getStringList(const std::string& key) const;
  // The keys present, sorted.
  std::vector<std::string> keys() const;

  const google::protobuf::Struct& values() const { return values_; }
  std::string toJson() const;

 private:
  const google::protobuf::Value* find(const std::string& key) const;
  google::protobuf::Struct values_;
};

}  // namespace cast
