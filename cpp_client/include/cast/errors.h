// The named errors of CAST (docs/client-protocol.md, "Errors").
//
// Every error corresponds to one gRPC status code. The library turns a failed
// call's status into the exception of the same name as in Python and Java, so
// a component handles `cast::LockedError` whichever server or language is on
// the other side. The message is the server's status details, unchanged.
#pragma once

#include <map>
#include <memory>
#include <stdexcept>
#include <string>

namespace grpc {
class Status;
class string_ref;
}  // namespace grpc

namespace cast {

// CastError is the base of every CAST error; code() is the gRPC status code
// name ("NOT_FOUND", ...), message() the server's explanation.
class CastError : public std::runtime_error {
 public:
  explicit CastError(const std::string& message, std::string code = "UNKNOWN");
  const std::string& code() const noexcept { return code_; }
  const std::string& message() const noexcept { return message_; }
  // The class name of the most derived error ("LockedError"), for logs.
  virtual const char* name() const noexcept { return "CastError"; }
  // Throws a copy of this error as its most derived type, so an error kept
  // as `std::shared_ptr<CastError>` can be rethrown and caught by its name.
  [[noreturn]] virtual void raise() const { throw *this; }

 private:
  std::string code_;
  std::string message_;
};

#define CAST_DECLARE_ERROR(Name, Code)                                      \
  class Name : public CastError {                                         \
   public:                                                                \
    explicit Name(const std::string& message) : CastError(message, Code) {} \
    const char* name() const noexcept override { return #Name; }          \
    [[noreturn]] void raise() const override { throw *this; }             \
  };

// A more precise error of a code another error already names: the server
// names it in the kErrorTrailer trailer, and `catch (const Base&)` still
// catches it.
#define CAST_DECLARE_PRECISE_ERROR(Name, Base)                          \
  class Name : public Base {                                            \
   public:                                                              \
    explicit Name(const std::string& message) : Base(message) {}        \
    const char* name() const noexcept override { return #Name; }        \
    [[noreturn]] void raise() const override { throw *this; }           \
  };

// An entry with this id already exists.
CAST_DECLARE_ERROR(AlreadyExistsError, "ALREADY_EXISTS")
// The entry, subarchitecture or task does not exist.
CAST_DECLARE_ERROR(NotFoundError, "NOT_FOUND")
// The entry's version is not the expected one (ABORTED).
CAST_DECLARE_ERROR(ConsistencyError, "ABORTED")
// The component may not write where it tried to.
CAST_DECLARE_ERROR(PermissionDeniedError, "PERMISSION_DENIED")
// Another component holds a lock that forbids this (FAILED_PRECONDITION);
// also an unlock of an entry the caller does not hold.
CAST_DECLARE_ERROR(LockedError, "FAILED_PRECONDITION")
// A bad id, type, value or request.
CAST_DECLARE_ERROR(InvalidArgumentError, "INVALID_ARGUMENT")
// The call had no valid token.
CAST_DECLARE_ERROR(UnauthenticatedError, "UNAUTHENTICATED")
// The call's deadline passed before it could complete.
CAST_DECLARE_ERROR(DeadlineExceededError, "DEADLINE_EXCEEDED")
// A watch fell behind (or asked for) revisions older than the kept history
// (OUT_OF_RANGE): read the current state, then watch again.
CAST_DECLARE_ERROR(HistoryExpiredError, "OUT_OF_RANGE")
// A configured limit was reached.
CAST_DECLARE_ERROR(ResourceExhaustedError, "RESOURCE_EXHAUSTED")
// The server cannot be reached.
CAST_DECLARE_ERROR(UnavailableError, "UNAVAILABLE")
// A bug: the server failed in a way it should not.
CAST_DECLARE_ERROR(InternalError, "INTERNAL")

// A task call its task's state does not allow, e.g. completing a task that is
// still waiting (FAILED_PRECONDITION).
CAST_DECLARE_PRECISE_ERROR(TaskStateError, LockedError)
// A lock or a task asked for by a component with no live session
// (FAILED_PRECONDITION): nothing would ever release it.
CAST_DECLARE_PRECISE_ERROR(NoSessionError, LockedError)
// A schema file registered again with other types (FAILED_PRECONDITION).
CAST_DECLARE_PRECISE_ERROR(SchemaConflictError, LockedError)

#undef CAST_DECLARE_ERROR
#undef CAST_DECLARE_PRECISE_ERROR

// The trailing metadata key in which the server names the error's class when
// several share its status code ("TaskStateError" next to FAILED_PRECONDITION).
inline constexpr const char* kErrorTrailer = "cast-error";

// The named error for a gRPC status code name ("NOT_FOUND", ...); an unknown
// code gives a plain CastError carrying that code. `errorName` (the
// kErrorTrailer trailer) picks a more precise class of that code, such as
// TaskStateError for FAILED_PRECONDITION; an unknown name, or one of another
// code, is ignored (as in Python's error_for_code).
std::shared_ptr<CastError> errorForCode(const std::string& codeName, const std::string& message,
                                        const std::string& errorName = "");

// The gRPC status code name of a numeric grpc::StatusCode ("UNKNOWN" if out
// of range).
std::string statusCodeName(int grpcStatusCode);

// The named error for a failed call's status; `errorName` as for
// errorForCode. UNAVAILABLE gets the Python client's explanation around
// gRPC's text, which says neither which side failed nor whether a write went
// through.
std::shared_ptr<CastError> errorForStatus(const grpc::Status& status, const std::string& errorName = "");

// The class the server named in a call's trailing metadata (kErrorTrailer),
// "" when it named none: pass `context.GetServerTrailingMetadata()` after the
// call (or stream) finished.
std::string errorTrailer(const std::multimap<grpc::string_ref, grpc::string_ref>& trailers);

// Throws errorForStatus(status, errorName) unless the status is OK.
void throwIfError(const grpc::Status& status, const std::string& errorName = "");

}  // namespace cast
