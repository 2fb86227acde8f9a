// Reads bridged ROS messages from a working memory with the C++ classes `cast ros-types` and
// cast_add_entry_types generated, and prints each as one JSON line: every field, and an FNV-1a
// hash of an image's pixels (the test compares it with the picture's).
//
// Args: type ("ros2.sensor_msgs.msg.Image" or "ros1.sensor_msgs.msg.Image"), sa (the WM), count (stop
// after that many changes).
#include <cstdint>
#include <iostream>
#include <sstream>
#include <string>

#include "cast/cast.h"
#include "ros1/sensor_msgs/msg/image.pb.h"
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

std::string quoted(const std::string& s) {
  std::string out = "\"";
  for (char c : s) {
    if (c == '"' || c == '\\') out += '\\';
    out += c;
  }
  return out + "\"";
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

}  // namespace

class RosEntryCheck : public cast::UnmanagedComponent {
 public:
  void configure(const cast::Args& args) override {
    type_ = args.getString("type");
    sa_ = args.getString("sa");
    count_ = args.getInt("count", 1);
  }

  void start() override {
    cast::ChangeFilter filter;
    filter.type = type_;
    filter.subarchitecture = sa_;
    filter.includeEntry = true;
    filter.operations = {cast::Operation::Add, cast::Operation::Overwrite};
    onChange(filter, [this](const cast::WorkingMemoryChange& change) {
      if (type_ == "ros2.sensor_msgs.msg.Image") {
        auto m = change.entry<ros2::sensor_msgs::msg::Image>().value;
        std::int64_t stamp = std::int64_t(m.header().stamp().sec()) * 1000000000 + m.header().stamp().nanosec();
        std::cout << imageJson(change.id(), m, stamp) << "}" << std::endl;
      } else {
        auto m = change.entry<ros1::sensor_msgs::msg::Image>().value;
        std::int64_t stamp = std::int64_t(m.header().stamp().secs()) * 1000000000 + m.header().stamp().nsecs();
        std::cout << imageJson(change.id(), m, stamp) << ",\"seq\":" << m.header().seq() << "}" << std::endl;
      }
      if (++seen_ >= count_) requestStop();
    });
    std::cout << "{\"ready\":true}" << std::endl;
  }

 private:
  std::string type_;
  std::string sa_;
  std::int64_t count_ = 1;
  std::int64_t seen_ = 0;
};

CAST_COMPONENT_MAIN(RosEntryCheck)
