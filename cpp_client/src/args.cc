#include "cast/args.h"

#include <google/protobuf/util/json_util.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <limits>

#include "cast/errors.h"

namespace cast {

namespace {

const char* kindName(const google::protobuf::Value& v) {
  switch (v.kind_case()) {
    case google::protobuf::Value::kNullValue: return "null";
    case google::protobuf::Value::kNumberValue: return "a number";
    case google::protobuf::Value::kStringValue: return "a string";
    case google::protobuf::Value::kBoolValue: return "a boolean";
    case google::protobuf::Value::kStructValue: return "an object";
    case google::protobuf::Value::kListValue: return "a list";
    default: return "empty";
  }
}

[[noreturn]] void wrongType(const std::string& key, const char* wanted, const google::protobuf::Value& v) {
  throw InvalidArgumentError("argument '" + key + "' must be " + wanted + ", got " + kindName(v));
}

}  // namespace

Args Args::fromJson(const std::string& json) {
  std::string text = json;
  if (std::all_of(text.begin(), text.end(), [](unsigned char c) { return std::isspace(c); })) text = "{}";
  // Struct's JSON form is a JSON object; anything else fails to parse.
  const auto first = text.find_first_not_of(" \t\r\n");
  if (text[first] != '{') throw InvalidArgumentError("CAST_ARGS must be a JSON object, got: " + json);
  google::protobuf::Struct values;
  auto status = google::protobuf::util::JsonStringToMessage(text, &values);
  if (!status.ok()) {
    throw InvalidArgumentError("CAST_ARGS is not valid JSON (" + std::string(status.message()) + "): " + json);
  }
  return Args(std::move(values));
}

const google::protobuf::Value* Args::find(const std::string& key) const {
  auto it = values_.fields().find(key);
  if (it == values_.fields().end() || it->second.kind_case() == google::protobuf::Value::kNullValue) return nullptr;
  return &it->second;
}

bool Args::has(const std::string& key) const { return find(key) != nullptr; }

std::string Args::getString(const std::string& key, const std::string& fallback) const {
  const auto* v = find(key);
  if (v == nullptr) return fallback;
  if (v->kind_case() != google::protobuf::Value::kStringValue) wrongType(key, "a string", *v);
  return v->string_value();
}

double Args::getDouble(const std::string& key, double fallback) const {
  const auto* v = find(key);
  if (v == nullptr) return fallback;
  if (v->kind_case() != google::protobuf::Value::kNumberValue) wrongType(key, "a number", *v);
  return v->number_value();
}

std::int64_t Args::getInt(const std::string& key, std::int64_t fallback) const {
  const auto* v = find(key);
  if (v == nullptr) return fallback;
  if (v->kind_case() != google::protobuf::Value::kNumberValue) wrongType(key, "an integer", *v);
  const double d = v->number_value();
  // JSON numbers are doubles: integers beyond 2^53 cannot arrive intact.
  if (std::floor(d) != d || std::fabs(d) > 9007199254740992.0) {
    throw InvalidArgumentError("argument '" + key + "' must be an integer, got " + std::to_string(d));
  }
  return static_cast<std::int64_t>(d);
}

bool Args::getBool(const std::string& key, bool fallback) const {
  const auto* v = find(key);
  if (v == nullptr) return fallback;
  if (v->kind_case() != google::protobuf::Value::kBoolValue) wrongType(key, "a boolean", *v);
  return v->bool_value();
}

std::vector<std::string> Args::getStringList(const std::string& key) const {
  const auto* v = find(key);
  if (v == nullptr) return {};
  if (v->kind_case() != google::protobuf::Value::kListValue) wrongType(key, "a list of strings", *v);
  std::vector<std::string> out;
  for (const auto& item : v->list_value().values()) {
    if (item.kind_case() != google::protobuf::Value::kStringValue) wrongType(key, "a list of strings", item);
    out.push_back(item.string_value());
  }
  return out;
}

std::vector<std::string> Args::keys() const {
  std::vector<std::string> out;
  for (const auto& kv : values_.fields()) out.push_back(kv.first);
  std::sort(out.begin(), out.end());
  return out;
}

std::string Args::toJson() const {
  std::string out;
  google::protobuf::util::JsonPrintOptions options;
  options.preserve_proto_field_names = true;
  (void)google::protobuf::util::MessageToJsonString(values_, &out, options);
  return out;
}

}  // namespace cast
