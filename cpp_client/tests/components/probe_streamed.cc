// cast_probe's commands for the streamed write path (see probe_streamed.h).
#include "probe_streamed.h"

#include <google/protobuf/wrappers.pb.h>

#include <array>
#include <future>
#include <vector>

#include "cast_testing.pb.h"

namespace cast::probe {

namespace {

// Waits for every future in call order; a refusal is recorded, not thrown, so
// that the writes after it are still reported.
std::string settle(std::vector<std::future<WriteResult>>& futures) {
  std::vector<std::string> revisions, versions, errors;
  for (size_t i = 0; i < futures.size(); ++i) {
    try {
      WriteResult r = futures[i].get();
      revisions.push_back(std::to_string(r.revision));
      versions.push_back(std::to_string(r.version));
    } catch (const CastError& e) {
      revisions.push_back("0");
      versions.push_back("0");
      errors.push_back(Object().unum("index", i).str("error", e.name()).str("code", e.code()).json());
    }
  }
  return Object().raw("revisions", array(revisions)).raw("versions", array(versions)).raw("errors", array(errors)).json();
}

std::string text(const google::protobuf::Struct& spec, const char* key) {
  auto it = spec.fields().find(key);
  return it == spec.fields().end() ? std::string() : it->second.string_value();
}

}  // namespace

std::string addAsync(Component& component, const std::string& prefix, int n) {
  std::vector<std::future<WriteResult>> futures;
  for (int i = 0; i < n; ++i) {
    cast::testing::Counter c;
    c.set_writer(component.componentId());
    c.set_value(i);
    futures.push_back(component.addAsync(prefix + "-" + std::to_string(i), c));
  }
  return settle(futures);
}

std::string overwriteAsync(Component& component, const std::string& id, int n) {
  std::vector<std::future<WriteResult>> futures;
  for (int i = 1; i <= n; ++i) {
    cast::testing::Counter c;
    c.set_writer(component.componentId());
    c.set_value(i);
    futures.push_back(component.overwriteAsync(id, c));
  }
  return settle(futures);
}

std::string bigWrite(Component& component, const std::string& id, const std::string& sa, std::size_t size) {
  google::protobuf::BytesValue value;
  std::string* bytes = value.mutable_value();
  bytes->resize(size);
  for (std::size_t i = 0; i < size; ++i) (*bytes)[i] = static_cast<char>(i % 251);
  WriteResult r = component.add(id, value, sa);
  return Object()
      .unum("revision", r.revision)
      .unum("version", r.version)
      .unum("size", size)
      .unum("crc32", crc32(*bytes))
      .json();
}

std::string bigRead(Component& component, const std::string& id, const std::string& sa) {
  auto e = component.getEntry<google::protobuf::BytesValue>(id, sa);
  return Object()
      .unum("size", e.value.value().size())
      .unum("crc32", crc32(e.value.value()))
      .unum("version", e.version)
      .str("author", e.author)
      .json();
}

WatchOptions watchOptions(const google::protobuf::Struct& spec) {
  WatchOptions options;
  const std::string delivery = text(spec, "delivery");
  if (delivery == "latest") options.delivery = Delivery::Latest;
  else if (!delivery.empty() && delivery != "queue")
    throw InvalidArgumentError("probe: delivery must be queue or latest, not " + delivery);
  const std::string priority = text(spec, "priority");
  if (priority == "high") options.priority = Priority::High;
  else if (priority == "low") options.priority = Priority::Low;
  else if (!priority.empty() && priority != "medium")
    throw InvalidArgumentError("probe: priority must be high, medium or low, not " + priority);
  return options;
}

std::chrono::milliseconds slowCallback(const google::protobuf::Struct& spec) {
  auto it = spec.fields().find("slow_ms");
  return std::chrono::milliseconds(it == spec.fields().end() ? 0 : static_cast<long>(it->second.number_value()));
}

void describeStreamed(Object& event, const WorkingMemoryChange& change) {
  event.unum("skipped", change.skipped()).unum("first_skipped_revision", change.firstSkippedRevision());
  if (change.hasEntry() && change.type() == "google.protobuf.BytesValue") {
    const auto entry = change.entry<google::protobuf::BytesValue>();
    event.unum("size", entry.value.value().size()).unum("crc32", crc32(entry.value.value()));
  }
}

std::uint32_t crc32(const std::string& data) {
  static const std::array<std::uint32_t, 256> table = [] {
    std::array<std::uint32_t, 256> t{};
    for (std::uint32_t i = 0; i < 256; ++i) {
      std::uint32_t c = i;
      for (int k = 0; k < 8; ++k) c = (c & 1) ? 0xEDB88320u ^ (c >> 1) : c >> 1;
      t[i] = c;
    }
    return t;
  }();
  std::uint32_t crc = 0xFFFFFFFFu;
  for (unsigned char b : data) crc = table[(crc ^ b) & 0xFF] ^ (crc >> 8);
  return crc ^ 0xFFFFFFFFu;
}

}  // namespace cast::probe
