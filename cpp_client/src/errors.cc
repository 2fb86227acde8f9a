#include "cast/errors.h"

#include <grpcpp/support/status.h>
#include <grpcpp/support/string_ref.h>

#include <array>

namespace cast {

CastError::CastError(const std::string& message, std::string code)
    : std::runtime_error(message), code_(std::move(code)), message_(message) {}

namespace {

// Indexed by grpc::StatusCode value (0 .. 16), names as gRPC spells them.
constexpr std::array<const char*, 17> kCodeNames = {
    "OK",          "CANCELLED",         "UNKNOWN",        "INVALID_ARGUMENT",   "DEADLINE_EXCEEDED",
    "NOT_FOUND",   "ALREADY_EXISTS",    "PERMISSION_DENIED", "RESOURCE_EXHAUSTED", "FAILED_PRECONDITION",
    "ABORTED",     "OUT_OF_RANGE",      "UNIMPLEMENTED",  "INTERNAL",           "UNAVAILABLE",
    "DATA_LOSS",   "UNAUTHENTICATED",
};

template <class E>
std::shared_ptr<CastError> make(const std::string& message) {
  return std::make_shared<E>(message);
}

// The error a status code maps to by itself, with no trailer.
std::shared_ptr<CastError> plainErrorForCode(const std::string& codeName, const std::string& message) {
  if (codeName == "ALREADY_EXISTS") return make<AlreadyExistsError>(message);
  if (codeName == "NOT_FOUND") return make<NotFoundError>(message);
  if (codeName == "ABORTED") return make<ConsistencyError>(message);
  if (codeName == "PERMISSION_DENIED") return make<PermissionDeniedError>(message);
  if (codeName == "FAILED_PRECONDITION") return make<LockedError>(message);
  if (codeName == "INVALID_ARGUMENT") return make<InvalidArgumentError>(message);
  if (codeName == "UNAUTHENTICATED") return make<UnauthenticatedError>(message);
  if (codeName == "DEADLINE_EXCEEDED") return make<DeadlineExceededError>(message);
  if (codeName == "OUT_OF_RANGE") return make<HistoryExpiredError>(message);
  if (codeName == "RESOURCE_EXHAUSTED") return make<ResourceExhaustedError>(message);
  if (codeName == "UNAVAILABLE") return make<UnavailableError>(message);
  if (codeName == "INTERNAL") return make<InternalError>(message);
  return std::make_shared<CastError>(message, codeName);
}

// The classes the server may name in the kErrorTrailer trailer, with their
// code (Python's errors._BY_NAME).
struct PreciseError {
  const char* name;
  const char* code;
  std::shared_ptr<CastError> (*make)(const std::string& message);
};
const PreciseError kPreciseErrors[] = {
    {"TaskStateError", "FAILED_PRECONDITION", make<TaskStateError>},
    {"NoSessionError", "FAILED_PRECONDITION", make<NoSessionError>},
    {"SchemaConflictError", "FAILED_PRECONDITION", make<SchemaConflictError>},
};

}  // namespace

std::string statusCodeName(int grpcStatusCode) {
  if (grpcStatusCode < 0 || grpcStatusCode >= static_cast<int>(kCodeNames.size())) return "UNKNOWN";
  return kCodeNames[static_cast<size_t>(grpcStatusCode)];
}

std::shared_ptr<CastError> errorForCode(const std::string& codeName, const std::string& message,
                                        const std::string& errorName) {
  for (const auto& precise : kPreciseErrors) {
    if (errorName == precise.name && codeName == precise.code) return precise.make(message);
  }
  return plainErrorForCode(codeName, message);
}

std::shared_ptr<CastError> errorForStatus(const grpc::Status& status, const std::string& errorName) {
  const std::string name = statusCodeName(static_cast<int>(status.error_code()));
  std::string details = status.error_message();
  if (name == "UNAVAILABLE") {
    return errorForCode(name, "server unavailable (" + details +
                                  "): a write made by this call may or may not have been applied; the client "
                                  "reconnects by itself, retry the call later");
  }
  return errorForCode(name, details.empty() ? name : details, errorName);
}

std::string errorTrailer(const std::multimap<grpc::string_ref, grpc::string_ref>& trailers) {
  auto it = trailers.find(kErrorTrailer);
  return it == trailers.end() ? std::string() : std::string(it->second.data(), it->second.size());
}

void throwIfError(const grpc::Status& status, const std::string& errorName) {
  if (!status.ok()) errorForStatus(status, errorName)->raise();
}

}  // namespace cast
