// A value read without copying (cast/views.h). Mirrors the Python client's
// client/views.py.
#include "cast/views.h"

#include <algorithm>
#include <ostream>
#include <stdexcept>

namespace cast {

namespace {

// A varint at `at`; moves `at` past it.
std::uint64_t varint(ByteSpan data, std::size_t& at, const std::string& what) {
  std::uint64_t value = 0;
  for (int shift = 0;; shift += 7) {
    if (at >= data.size() || shift > 63) {
      throw InvalidArgumentError(what + ": the value ends inside a varint: it is not a serialised message");
    }
    const auto byte = static_cast<std::uint8_t>(data[at++]);
    value |= static_cast<std::uint64_t>(byte & 0x7f) << shift;
    if (byte < 0x80) return value;
  }
}

}  // namespace

ByteSpan ByteSpan::subspan(std::size_t offset, std::size_t count) const {
  if (offset > size_) throw std::out_of_range("ByteSpan::subspan: offset past the end");
  return ByteSpan(data_ + offset, count == npos ? size_ - offset : std::min(count, size_ - offset));
}

namespace {

// The bytes of top-level field `number` of the serialised message `data`
// (see ValueView::field); `what` names the value in errors.
ByteSpan fieldOf(ByteSpan data, int number, const std::string& what) {
  ByteSpan found(data.data(), 0);
  std::size_t at = 0;
  const std::size_t size = data.size();
  while (at < size) {
    const std::uint64_t key = varint(data, at, what);
    const std::uint64_t tag = key >> 3;
    const unsigned kind = static_cast<unsigned>(key & 7);
    if (kind == 0) {
      varint(data, at, what);
    } else if (kind == 1) {
      at += 8;
    } else if (kind == 5) {
      at += 4;
    } else if (kind == 2) {
      const std::uint64_t length = varint(data, at, what);
      if (length > size - at) {
        throw InvalidArgumentError(what + ": field " + std::to_string(tag) +
                                   " runs past the end: it is not a serialised message");
      }
      if (tag == static_cast<std::uint64_t>(number)) found = ByteSpan(data.data() + at, length);
      at += length;
    } else {
      throw InvalidArgumentError(what + ": field " + std::to_string(tag) + " has wire type " + std::to_string(kind) +
                                 ", which a view does not read");
    }
    if (tag == static_cast<std::uint64_t>(number) && kind != 2) {
      throw InvalidArgumentError(what + ": field " + std::to_string(number) +
                                 " is a number, not bytes, a string or a message");
    }
    if (at > size) {
      throw InvalidArgumentError(what + ": field " + std::to_string(tag) +
                                 " runs past the end: it is not a serialised message");
    }
  }
  return found;
}

}  // namespace

const detail::EntryRecord& ValueView::held() const {
  if (!record_) throw InvalidArgumentError("this view was released: read the entry again");
  return *record_;
}

ByteSpan ValueView::data() const {
  const std::string_view bytes = held().bytes();
  return ByteSpan(reinterpret_cast<const std::byte*>(bytes.data()), bytes.size());
}

ByteSpan ValueView::field(int number) const {
  const detail::EntryRecord& r = held();
  return fieldOf(data(), number, "entry '" + r.address.id + "' in subarchitecture '" +
                                             r.address.subarchitecture + "'");
}

std::ostream& operator<<(std::ostream& os, const ValueView& view) {
  try {
    const ByteSpan bytes = view.data();
    return os << "ValueView(" << view.address().subarchitecture << "/" << view.id() << " type=" << view.type()
              << " v=" << view.version() << " " << bytes.size() << " bytes in "
              << (view.shared() ? "shared memory" : "bytes") << ")";
  } catch (const InvalidArgumentError&) {
    return os << "ValueView(released)";
  }
}

ValueView WorkingMemoryChange::view() const {
  if (!ev_->entry) throw InvalidArgumentError("this change carries no entry: ask for it with includeEntry");
  // Shares the event: the value stays lent while the view or the change lives.
  return ValueView(std::shared_ptr<const detail::EntryRecord>(ev_, &*ev_->entry));
}

}  // namespace cast
