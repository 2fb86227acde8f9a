// What a cast::Loan holds (cast/loan.h), private to the library: the value's
// serialised bytes with the loaned field last (the header: the value's other
// fields, then the field's key and length; then the payload, the field's
// bytes, which the user fills), in a region of a session's staging area or in
// private memory. The component makes loans and checks their writes
// (component.cc); the transport places them and writes them (shm.cc). The
// staged bytes are an ordinary serialised message, so the server needs
// nothing new (protobuf takes fields in any order; for a field given twice,
// the last).
#pragma once

#include <google/protobuf/message.h>

#include <cstddef>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

#include "cast/loan.h"
#include "shm_session.h"

namespace cast::detail {

class LoanState {
 public:
  // Private memory: `header`, then `size` bytes.
  LoanState(std::string header, std::size_t size);
  // In `region` of `session`'s staging area (its pad, then `header`, written
  // here, then `size` bytes); the loan keeps the mapping, and gives the
  // region back when it is spent unwritten, if the session still lives.
  LoanState(std::string_view header, std::size_t size, const std::shared_ptr<ClientSession>& session,
            Reserved region);
  // spend().
  ~LoanState();
  LoanState(const LoanState&) = delete;
  LoanState& operator=(const LoanState&) = delete;

  // The subarchitecture it was taken for (the component's own for "") and
  // the value's full type name: what its write must match, and the entry's type.
  std::string sa;
  std::string type;

  // The payload's first byte; nullptr once spent.
  std::byte* payload() const noexcept { return payload_; }
  std::size_t size() const noexcept { return size_; }
  std::size_t headerSize() const noexcept { return headerSize_; }
  bool shared() const noexcept { return shared_; }
  // Written or closed: its buffer is gone, and it is not written again.
  bool spent() const noexcept { return spent_; }

  // For a write that goes on `writer` (the SA's server's live writer
  // session): the loan's region, when it is in `writer`'s staging area and
  // that session still lives. The write names it (no copy) and gives it back
  // after its reply as it gives back a staged value's (unstage), so the loan
  // no longer does. nullopt: private memory, or a session that ended or was
  // replaced (a renewed token) since the loan was taken.
  std::optional<Staged> handOver(const std::shared_ptr<ClientSession>& writer);
  // The serialised value (header, then payload) for a write that sends
  // bytes: moved out of private memory, or copied out of the region, which
  // is given back at once (its session is not the one the write goes on).
  // The buffer is gone after it.
  std::string takeBytes();
  // The loan was written (whatever the outcome) or closed: a region not
  // handed over goes back to the staging area if its session still lives,
  // the memory is let go. Idempotent.
  void spend() noexcept;

  // For tests and diagnostics: the region in the staging area (nullopt for
  // private memory); the session it is in; whether its write named it in
  // place (handOver).
  const std::optional<Staged>& region() const noexcept { return region_; }
  std::shared_ptr<ClientSession> session() const { return session_.lock(); }
  bool writtenInPlace() const noexcept { return handedOver_; }

 private:
  // Gives the region back (if it is still the loan's and its session lives)
  // and lets the memory go.
  void letGo() noexcept;

  std::size_t headerSize_ = 0;
  std::size_t size_ = 0;
  bool shared_ = false;
  bool spent_ = false;
  bool handedOver_ = false;
  std::byte* payload_ = nullptr;
  std::string private_;  // header + payload, when not shared
  // When shared: the session (not kept alive by a loan), the staging area's
  // mapping (kept mapped by it), the region.
  std::weak_ptr<ClientSession> session_;
  std::shared_ptr<Mapping> staging_;
  std::optional<Staged> region_;
};

// How the library reaches a Loan's state (Loan's private parts are for it alone).
class LoanAccess {
 public:
  // A loan holding `state`.
  static Loan make(std::unique_ptr<LoanState> state) noexcept { return Loan(std::move(state)); }
  // Its state; nullptr for a moved-from or default-constructed loan.
  static LoanState* state(const Loan& loan) noexcept { return loan.state_.get(); }
};

// What precedes a loan's payload: `value` serialised, then the key of its
// field `field` (number << 3 | 2) and `size`, each a varint.
// InvalidArgumentError, saying what would do, when `field` is not a
// top-level singular bytes field of the value's type, already holds bytes,
// or the value would pass a protobuf message's 2 GiB.
std::string loanHeader(const google::protobuf::Message& value, const std::string& field, std::size_t size);

}  // namespace cast::detail
