// A value read without copying: cast::ValueView (Python: cast.ValueView;
// Java: cast.client.ValueView).
//
// component.getView(id) and change.view() give an entry's value, serialised,
// as read-only bytes: on the server's host, a large value is the server's
// shared memory it was lent in (nothing copied, however large); elsewhere,
// the bytes received. view.field(n) is the bytes of one top-level field (an
// image's pixels in a `bytes` field), still not copied:
//
//   cast::ValueView view = component.getView("camera");
//   cast::ByteSpan pixels = view.field(1);
//   cv::Mat image(480, 640, CV_8UC3, const_cast<std::byte*>(pixels.data()));  // read it only
//
// The bytes never change while the view is held; the view gives the value
// back when it is destroyed or released. Spans taken from it are valid until
// then. docs/cpp.md, "Large values".
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <string_view>
#include <utility>

#if __cplusplus >= 202002L && __has_include(<span>)
#include <span>
#endif

#include "cast/detail/records.h"
#include "cast/errors.h"
#include "cast/types.h"

namespace cast {

// Read-only bytes that are not a copy: what std::span<const std::byte> is in
// C++20 (this library builds as C++17; a C++20 program converts a ByteSpan
// to std::span<const std::byte> implicitly).
class ByteSpan {
 public:
  static constexpr std::size_t npos = static_cast<std::size_t>(-1);

  constexpr ByteSpan() noexcept = default;
  constexpr ByteSpan(const std::byte* data, std::size_t size) noexcept : data_(data), size_(size) {}

  constexpr const std::byte* data() const noexcept { return data_; }
  constexpr std::size_t size() const noexcept { return size_; }
  constexpr bool empty() const noexcept { return size_ == 0; }
  constexpr const std::byte* begin() const noexcept { return data_; }
  constexpr const std::byte* end() const noexcept { return data_ + size_; }
  constexpr const std::byte& operator[](std::size_t i) const noexcept { return data_[i]; }
  // `count` bytes from `offset` (to the end with npos); std::out_of_range past the end.
  ByteSpan subspan(std::size_t offset, std::size_t count = npos) const;
  // The same bytes as characters, for APIs that take them (protobuf's
  // ParseFromArray, std::string's constructor, a checksum over chars).
  std::string_view chars() const noexcept {
    return std::string_view(reinterpret_cast<const char*>(data_), size_);
  }

#if __cplusplus >= 202002L && __has_include(<span>)
  operator std::span<const std::byte>() const noexcept { return {data_, size_}; }
#endif

 private:
  const std::byte* data_ = nullptr;
  std::size_t size_ = 0;
};

// An entry's value, serialised, as read-only bytes that are not a copy, with
// the entry's metadata as Entry<T> has it. Move-only: the value stays lent
// (on the server's host) until the view is destroyed or release()d, and the
// bytes never change meanwhile. Calls on a released (or moved-from) view
// throw InvalidArgumentError.
class ValueView {
 public:
  // A released view (assign one to it).
  ValueView() = default;
  // The view of a record the transport returned (Component::getView and
  // WorkingMemoryChange::view make them).
  explicit ValueView(std::shared_ptr<const detail::EntryRecord> record) : record_(std::move(record)) {}
  ValueView(ValueView&& other) noexcept = default;
  ValueView& operator=(ValueView&& other) noexcept = default;
  ValueView(const ValueView&) = delete;
  ValueView& operator=(const ValueView&) = delete;
  ~ValueView() = default;

  // Where the entry lives, and its id.
  const WorkingMemoryAddress& address() const { return held().address; }
  const std::string& id() const { return held().address.id; }
  // The full message name of the value.
  const std::string& type() const { return held().type; }
  // The entry's version this value is of, who wrote it, the WM revision of
  // the write, and when (server clock, ns since the epoch).
  std::uint64_t version() const { return held().version; }
  const std::string& author() const { return held().author; }
  std::uint64_t revision() const { return held().revision; }
  std::int64_t modifiedNs() const { return held().modifiedNs; }
  // Whether the bytes are the server's shared memory (lent on its host), not
  // a received copy.
  bool shared() const { return held().lent != nullptr; }
  // The serialised value, read-only.
  ByteSpan data() const;
  // The bytes of top-level field `number` (a bytes, string or message
  // field), read-only, not copied; empty when the field is absent (the last
  // occurrence wins, as when protobuf parses). InvalidArgumentError for a
  // field of another kind (a number) or bytes that are not a message.
  ByteSpan field(int number) const;
  // The value as a T message (a copy, as Component::get<T> gives).
  template <class T>
  T decode() const {
    return detail::decodeEntry<T>(held());
  }
  // Gives the value back now (the destructor does it otherwise); spans taken
  // from the view end with it. Idempotent.
  void release() noexcept { record_.reset(); }

 private:
  const detail::EntryRecord& held() const;
  std::shared_ptr<const detail::EntryRecord> record_;
};

std::ostream& operator<<(std::ostream& os, const ValueView& view);

}  // namespace cast
