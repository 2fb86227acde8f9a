// A large value written in place: cast::Loan (Python: cast.client.Loan;
// Java: cast.client.Loan).
//
// Writing a large value the usual way makes its bytes, serialises the message
// (a copy) and, on the server's host, copies that into the staging area the
// server reads it from (another). A loan skips both: the component asks for
// the place of one top-level `bytes` field of the value, fills it there, and
// writes the loan instead of the message:
//
//   Frame frame;  // every field set but the pixels
//   frame.set_width(640);
//   frame.set_height(480);
//   cast::Loan loan = component.loan(frame, "pixels", 640 * 480 * 3);
//   camera.grab(loan.buffer().data(), loan.buffer().size());
//   component.overwrite("camera", std::move(loan));
//
// On the server's host, with shared memory on and a value of at least the
// session's threshold, the buffer is in the session's staging area and the
// write names it: nothing is copied on the client (shared() is true). Else
// the buffer is private memory and the write sends bytes as any other.
// Readers get the same value either way. docs/cpp.md, "Writing a large value
// in place (loans)".
#pragma once

#include <cstddef>
#include <memory>
#include <stdexcept>

#if __cplusplus >= 202002L && __has_include(<span>)
#include <span>
#endif

#include "cast/views.h"

namespace cast {

namespace detail {
class LoanState;
class LoanAccess;
}  // namespace detail

// Writable bytes in place: what std::span<std::byte> is in C++20 (this
// library builds as C++17; a C++20 program converts a MutableByteSpan to
// std::span<std::byte> implicitly). A loan's buffer.
class MutableByteSpan {
 public:
  static constexpr std::size_t npos = static_cast<std::size_t>(-1);

  constexpr MutableByteSpan() noexcept = default;
  constexpr MutableByteSpan(std::byte* data, std::size_t size) noexcept : data_(data), size_(size) {}

  constexpr std::byte* data() const noexcept { return data_; }
  constexpr std::size_t size() const noexcept { return size_; }
  constexpr bool empty() const noexcept { return size_ == 0; }
  constexpr std::byte* begin() const noexcept { return data_; }
  constexpr std::byte* end() const noexcept { return data_ + size_; }
  constexpr std::byte& operator[](std::size_t i) const noexcept { return data_[i]; }
  // `count` bytes from `offset` (to the end with npos); std::out_of_range past the end.
  MutableByteSpan subspan(std::size_t offset, std::size_t count = npos) const {
    if (offset > size_) throw std::out_of_range("subspan offset past the end of a MutableByteSpan");
    return MutableByteSpan(data_ + offset, count == npos || count > size_ - offset ? size_ - offset : count);
  }
  // The same bytes, read-only.
  constexpr operator ByteSpan() const noexcept { return ByteSpan(data_, size_); }

#if __cplusplus >= 202002L && __has_include(<span>)
  operator std::span<std::byte>() const noexcept { return {data_, size_}; }
#endif

 private:
  std::byte* data_ = nullptr;
  std::size_t size_ = 0;
};

// The place of one top-level `bytes` field of a value, to fill before the
// value is written (Component::loan; the writes take it as a Loan&&). Its
// buffer's first contents are unspecified. Written once: after its write
// (add, overwrite, addAsync, overwriteAsync, whatever the outcome) it is
// spent, and its buffer must not be touched any more (it may be the server's
// staging area, which a later write reuses); writing it again, or after
// close(), throws InvalidArgumentError. Move-only; used by one thread at a
// time.
class Loan {
 public:
  // A closed loan (assign one to it).
  Loan() noexcept;
  Loan(Loan&& other) noexcept;
  // Closes the loan it replaces.
  Loan& operator=(Loan&& other) noexcept;
  Loan(const Loan&) = delete;
  Loan& operator=(const Loan&) = delete;
  // close().
  ~Loan();

  // The field's bytes, writable, in place: size() of them. Empty once the
  // loan was written or closed.
  MutableByteSpan buffer() const noexcept;
  // The field's length, as the loan was taken.
  std::size_t size() const noexcept;
  // Whether the buffer is in the session's staging area, so that the write
  // copies nothing; false when it is private memory (another host, shared
  // memory off, a value under the threshold, no room in the staging area),
  // and the write sends bytes.
  bool shared() const noexcept;
  // Gives an unwritten loan's place back to the staging area; nothing for a
  // written or closed loan. The destructor calls it.
  void close() noexcept;

 private:
  friend class detail::LoanAccess;
  explicit Loan(std::unique_ptr<detail::LoanState> state) noexcept;
  std::unique_ptr<detail::LoanState> state_;
};

}  // namespace cast
