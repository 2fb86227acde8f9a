// Reads bridged ROS messages from working memories with the C++ classes `cast ros-types` and
// cast_add_entry_types generated, and prints each as one JSON line with every field (an image's
// pixels as their size and FNV-1a hash, other bytes as hex), for the test to compare with what the
// ROS publisher sent.
//
// Each line starts with the entry type ("type"), then "id", then the fields.
//
// Args: watch, an object: entry type -> {"sa": the WM, "count": stop after that many changes of the
// type}; the component stops once every type has reached its count. Types: ros2.sensor_msgs.msg.Image,
// ros2.geometry_msgs.msg.PoseStamped, ros2.cast_test_msgs.msg.Reading (the test's own package),
// ros1.sensor_msgs.msg.Image.
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstdint>
#include <functional>
#include <iostream>
#include <map>
#include <mutex>
#include <sstream>
#include <stdexcept>
#include <string>

#include "cast/cast.h"
#include "ros1/sensor_msgs/msg/image.pb.h"
#include "ros2/cast_test_msgs/msg/reading.pb.h"
#include "ros2/geometry_msgs/msg/pose_stamped.pb.h"
#include "ros2/sensor_msgs/msg/image.pb.h"

namespace {

std::string fnv1a(const std::string& data) {
  std::uint64_t h = 0xcbf29ce484222325ULL;
  for (unsigned char c : data) {
    h ^= c;
    h *= 0x100000001b3ULL;
  }
  std::ostringstream out;
  out << std::hex << h;
  return out.str();
}

std::string hex(const std::string& data) {
  static const char digits[] = "0123456789abcdef";
  std::string out;
  for (unsigned char c : data) {
    out += digits[c >> 4];
    out += digits[c & 15];
  }
  return out;
}

// UTF-8 passes through unchanged (the test reads the output as UTF-8).
std::string quoted(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += c;
    } else if (static_cast<unsigned char>(c) < 0x20) {
      char escape[8];
      std::snprintf(escape, sizeof escape, "\\u%04x", c);
      out += escape;
    } else {
      out += c;
    }
  }
  return out + "\"";
}

// The shortest text that reads back as the same value; Infinity and NaN as Python's json reads them,
// and always with a point or exponent, so that -0.0 stays a negative zero.
template <class Float>
std::string number(Float v) {
  if (std::isnan(v)) return "NaN";
  if (std::isinf(v)) return v > 0 ? "Infinity" : "-Infinity";
  char buffer[64];
  auto end = std::to_chars(buffer, buffer + sizeof buffer, v).ptr;
  std::string out(buffer, end);
  if (out.find_first_of(".e") == std::string::npos) out += ".0";
  return out;
}

template <class Repeated, class Format>
std::string list(const Repeated& values, Format format) {
  std::string out = "[";
  for (int i = 0; i < values.size(); ++i) out += (i ? "," : "") + format(values.Get(i));
  return out + "]";
}

std::string header(const ros2::std_msgs::msg::Header& h) {
  std::ostringstream out;
  out << "{\"stamp\":{\"sec\":" << h.stamp().sec() << ",\"nanosec\":" << h.stamp().nanosec()
      << "},\"frame_id\":" << quoted(h.frame_id()) << "}";
  return out.str();
}

std::string point(const ros2::geometry_msgs::msg::Point& p) {
  return "{\"x\":" + number(p.x()) + ",\"y\":" + number(p.y()) + ",\"z\":" + number(p.z()) + "}";
}

template <class Image>
std::string imageJson(const std::string& id, const Image& m, std::int64_t stampNs) {
  std::ostringstream out;
  out << "{\"id\":" << quoted(id) << ",\"frame_id\":" << quoted(m.header().frame_id()) << ",\"stamp_ns\":" << stampNs
      << ",\"height\":" << m.height() << ",\"width\":" << m.width() << ",\"encoding\":" << quoted(m.encoding())
      << ",\"is_bigendian\":" << m.is_bigendian() << ",\"step\":" << m.step() << ",\"size\":" << m.data().size()
      << ",\"fnv\":" << quoted(fnv1a(m.data()));
  return out.str();
}

std::string ros2Image(const cast::WorkingMemoryChange& change) {
  auto m = change.entry<ros2::sensor_msgs::msg::Image>().value;
  std::int64_t stamp = std::int64_t(m.header().stamp().sec()) * 1000000000 + m.header().stamp().nanosec();
  return imageJson(change.id(), m, stamp) + "}";
}

std::string ros1Image(const cast::WorkingMemoryChange& change) {
  auto m = change.entry<ros1::sensor_msgs::msg::Image>().value;
  std::int64_t stamp = std::int64_t(m.header().stamp().secs()) * 1000000000 + m.header().stamp().nsecs();
  return imageJson(change.id(), m, stamp) + ",\"seq\":" + std::to_string(m.header().seq()) + "}";
}

std::string poseStamped(const cast::WorkingMemoryChange& change) {
  auto m = change.entry<ros2::geometry_msgs::msg::PoseStamped>().value;
  const auto& q = m.pose().orientation();
  return "{\"id\":" + quoted(change.id()) + ",\"header\":" + header(m.header()) + ",\"pose\":{\"position\":" +
         point(m.pose().position()) + ",\"orientation\":{\"x\":" + number(q.x()) + ",\"y\":" + number(q.y()) +
         ",\"z\":" + number(q.z()) + ",\"w\":" + number(q.w()) + "}}}";
}

std::string reading(const cast::WorkingMemoryChange& change) {
  auto m = change.entry<ros2::cast_test_msgs::msg::Reading>().value;
  std::ostringstream out;
  out << "{\"id\":" << quoted(change.id()) << ",\"header\":" << header(m.header()) << ",\"level\":" << m.level()
      << ",\"value\":" << number(m.value())
      << ",\"triple\":" << list(m.triple(), [](std::int32_t v) { return std::to_string(v); })
      << ",\"label\":" << quoted(m.label()) << ",\"points\":" << list(m.points(), point)
      << ",\"gains\":" << list(m.gains(), [](float v) { return number(v); }) << ",\"blob\":" << quoted(hex(m.blob()))
      << ",\"code\":" << quoted(hex(m.code())) << ",\"count\":" << m.count() << ",\"window\":{\"sec\":"
      << m.window().sec() << ",\"nanosec\":" << m.window().nanosec() << "}}";
  return out.str();
}

const std::map<std::string, std::function<std::string(const cast::WorkingMemoryChange&)>> kFormats = {
    {"ros2.sensor_msgs.msg.Image", ros2Image},
    {"ros2.geometry_msgs.msg.PoseStamped", poseStamped},
    {"ros2.cast_test_msgs.msg.Reading", reading},
    {"ros1.sensor_msgs.msg.Image", ros1Image},
};

}  // namespace

class RosEntryCheck : public cast::UnmanagedComponent {
 public:
  void configure(const cast::Args& args) override {
    auto watch = args.values().fields().find("watch");
    if (watch == args.values().fields().end() || !watch->second.has_struct_value()) {
      throw std::invalid_argument("args.watch: an object of entry type -> {\"sa\": ..., \"count\": ...} is needed");
    }
    for (const auto& [type, spec] : watch->second.struct_value().fields()) {
      if (kFormats.count(type) == 0) throw std::invalid_argument("args.watch: no decoder for type " + type);
      const auto& fields = spec.struct_value().fields();
      auto sa = fields.find("sa");
      auto count = fields.find("count");
      if (sa == fields.end() || count == fields.end()) {
        throw std::invalid_argument("args.watch." + type + ": both \"sa\" and \"count\" are needed");
      }
      watched_[type] = {sa->second.string_value(), static_cast<std::int64_t>(count->second.number_value())};
    }
  }

  void start() override {
    for (const auto& [type, want] : watched_) {
      cast::ChangeFilter filter;
      filter.type = type;
      filter.subarchitecture = want.first;
      filter.includeEntry = true;
      filter.operations = {cast::Operation::Add, cast::Operation::Overwrite};
      const auto& format = kFormats.at(type);
      onChange(filter, [this, type = type, &format](const cast::WorkingMemoryChange& change) {
        std::lock_guard<std::mutex> lock(mutex_);
        if (seen_[type] >= watched_.at(type).second) return;  // one type's count reached: only the others now
        std::cout << "{\"type\":" << quoted(type) << "," << format(change).substr(1) << std::endl;
        ++seen_[type];
        for (const auto& [t, w] : watched_) {
          if (seen_[t] < w.second) return;
        }
        requestStop();
      });
    }
    std::cout << "{\"ready\":true}" << std::endl;
  }

 private:
  std::map<std::string, std::pair<std::string, std::int64_t>> watched_;  // type -> (sa, count)
  std::map<std::string, std::int64_t> seen_;
  std::mutex mutex_;
};

CAST_COMPONENT_MAIN(RosEntryCheck)
