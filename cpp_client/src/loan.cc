// A large value written in place (cast/loan.h): the Loan a component holds,
// and the state behind it (loan_state.h). Mirrors the Python client's
// client/loan.py.
#include "cast/loan.h"

#include <google/protobuf/descriptor.h>

#include <cstdint>
#include <cstring>
#include <limits>
#include <utility>

#include "cast/errors.h"
#include "loan_state.h"
#include "transport.h"

namespace cast {

// ---------------------------------------------------------------- Loan

Loan::Loan() noexcept = default;

Loan::Loan(std::unique_ptr<detail::LoanState> state) noexcept : state_(std::move(state)) {}

Loan::Loan(Loan&& other) noexcept = default;

Loan& Loan::operator=(Loan&& other) noexcept {
  if (this != &other) {
    close();
    state_ = std::move(other.state_);
  }
  return *this;
}

Loan::~Loan() { close(); }

MutableByteSpan Loan::buffer() const noexcept {
  if (!state_ || state_->payload() == nullptr) return {};
  return MutableByteSpan(state_->payload(), state_->size());
}

std::size_t Loan::size() const noexcept { return state_ ? state_->size() : 0; }

bool Loan::shared() const noexcept { return state_ && state_->shared(); }

void Loan::close() noexcept {
  if (state_) state_->spend();
}

namespace detail {

// ---------------------------------------------------------------- LoanState

LoanState::LoanState(std::string header, std::size_t size)
    : headerSize_(header.size()), size_(size), private_(std::move(header)) {
  private_.resize(headerSize_ + size);  // the payload's first contents are unspecified (zeros here)
  payload_ = reinterpret_cast<std::byte*>(private_.data()) + headerSize_;
}

LoanState::LoanState(std::string_view header, std::size_t size, const std::shared_ptr<ClientSession>& session,
                     Reserved region)
    : headerSize_(header.size()),
      size_(size),
      shared_(true),
      session_(session),
      staging_(std::move(region.staging)),
      region_(region.staged) {
  char* at = staging_->data() + region_->offset;
  std::memcpy(at, header.data(), header.size());
  payload_ = reinterpret_cast<std::byte*>(at + header.size());
}

LoanState::~LoanState() { spend(); }

std::optional<Staged> LoanState::handOver(const std::shared_ptr<ClientSession>& writer) {
  if (spent_ || !region_ || !writer || writer->dead() || writer != session_.lock()) return std::nullopt;
  handedOver_ = true;
  return region_;
}

std::string LoanState::takeBytes() {
  std::string bytes;
  if (!shared_) {
    bytes = std::move(private_);
  } else if (staging_) {
    const char* at = staging_->data() + region_->offset;
    bytes.assign(at, headerSize_ + size_);
  }
  letGo();
  return bytes;
}

void LoanState::spend() noexcept {
  spent_ = true;
  letGo();
}

void LoanState::letGo() noexcept {
  payload_ = nullptr;
  if (region_ && !handedOver_) {
    if (std::shared_ptr<ClientSession> session = session_.lock()) {
      try {
        session->unstage(*region_, true);  // nothing of it was sent: the region is free
      } catch (...) {  // a mutex that cannot be locked: the region stays taken until the session ends
      }
    }
  }
  region_.reset();
  session_.reset();
  staging_.reset();  // the last holder of a session that ended unmaps its staging area here
  std::string().swap(private_);
}

// ---------------------------------------------------------------- the header

namespace {

constexpr std::uint32_t kLengthDelimited = 2;  // protobuf's wire type of a bytes field

void appendLoanVarint(std::string& out, std::uint64_t n) {
  while (n >= 0x80) {
    out.push_back(static_cast<char>((n & 0x7f) | 0x80));
    n >>= 7;
  }
  out.push_back(static_cast<char>(n));
}

bool loanable(const google::protobuf::FieldDescriptor& field) {
  return field.type() == google::protobuf::FieldDescriptor::TYPE_BYTES && !field.is_repeated();
}

}  // namespace

std::string loanHeader(const google::protobuf::Message& value, const std::string& field, std::size_t size) {
  const google::protobuf::Descriptor* type = value.GetDescriptor();
  const google::protobuf::FieldDescriptor* found = type->FindFieldByName(field);
  if (found == nullptr) {
    std::string fields;
    for (int i = 0; i < type->field_count(); ++i) {
      if (!loanable(*type->field(i))) continue;
      fields += (fields.empty() ? "" : ", ") + type->field(i)->name();
    }
    throw InvalidArgumentError(type->name() + " has no field '" + field +
                               "': a loan is taken of one of its top-level bytes fields (" +
                               (fields.empty() ? "it has none" : fields) + ")");
  }
  if (!loanable(*found)) {
    throw InvalidArgumentError("field '" + field + "' of " + type->full_name() + " is a " +
                               (found->is_repeated() ? "repeated " : "") + found->type_name() +
                               ": a loan is taken of a top-level singular bytes field");
  }
  std::string scratch;
  const std::size_t held = value.GetReflection()->GetStringReference(value, found, &scratch).size();
  if (held > 0) {
    throw InvalidArgumentError("field '" + field + "' of " + type->full_name() + " already holds " +
                               std::to_string(held) + " bytes: leave it empty, the loan's buffer is its bytes");
  }
  std::string header = value.SerializePartialAsString();
  appendLoanVarint(header, static_cast<std::uint64_t>(found->number()) << 3 | kLengthDelimited);
  appendLoanVarint(header, size);
  // protobuf parses no message of 2 GiB or more.
  constexpr std::size_t kMaxMessage = static_cast<std::size_t>(std::numeric_limits<std::int32_t>::max());
  if (size > kMaxMessage - header.size()) {
    throw InvalidArgumentError("a loan of " + std::to_string(size) + " bytes of field '" + field + "' of " +
                               type->full_name() +
                               " makes a message over protobuf's 2 GiB: take a loan of fewer bytes");
  }
  return header;
}

std::unique_ptr<LoanState> privateLoan(std::string header, std::size_t size) {
  return std::make_unique<LoanState>(std::move(header), size);
}

std::string loanBytes(LoanState& loan) { return loan.takeBytes(); }

}  // namespace detail
}  // namespace cast
