// Status codes map to the same named errors as in Python and Java
// (docs/client-protocol.md, "Errors").
#include <grpcpp/support/status.h>
#include <grpcpp/support/string_ref.h>
#include <gtest/gtest.h>

#include <map>

#include "cast/errors.h"

namespace {

using cast::CastError;

struct Case {
  grpc::StatusCode code;
  const char* codeName;
  const char* className;
};

const Case kCases[] = {
    {grpc::StatusCode::ALREADY_EXISTS, "ALREADY_EXISTS", "AlreadyExistsError"},
    {grpc::StatusCode::NOT_FOUND, "NOT_FOUND", "NotFoundError"},
    {grpc::StatusCode::ABORTED, "ABORTED", "ConsistencyError"},
    {grpc::StatusCode::PERMISSION_DENIED, "PERMISSION_DENIED", "PermissionDeniedError"},
    {grpc::StatusCode::FAILED_PRECONDITION, "FAILED_PRECONDITION", "LockedError"},
    {grpc::StatusCode::INVALID_ARGUMENT, "INVALID_ARGUMENT", "InvalidArgumentError"},
    {grpc::StatusCode::UNAUTHENTICATED, "UNAUTHENTICATED", "UnauthenticatedError"},
    {grpc::StatusCode::DEADLINE_EXCEEDED, "DEADLINE_EXCEEDED", "DeadlineExceededError"},
    {grpc::StatusCode::OUT_OF_RANGE, "OUT_OF_RANGE", "HistoryExpiredError"},
    {grpc::StatusCode::RESOURCE_EXHAUSTED, "RESOURCE_EXHAUSTED", "ResourceExhaustedError"},
    {grpc::StatusCode::UNAVAILABLE, "UNAVAILABLE", "UnavailableError"},
    {grpc::StatusCode::INTERNAL, "INTERNAL", "InternalError"},
};

TEST(Errors, EveryStatusCodeMapsToItsNamedError) {
  for (const auto& c : kCases) {
    auto err = cast::errorForStatus(grpc::Status(c.code, "details of " + std::string(c.codeName)));
    ASSERT_NE(err, nullptr);
    EXPECT_STREQ(err->name(), c.className) << c.codeName;
    EXPECT_EQ(err->code(), c.codeName);
    if (c.code != grpc::StatusCode::UNAVAILABLE) {
      // The message is the server's details, unchanged.
      EXPECT_EQ(err->message(), "details of " + std::string(c.codeName));
    }
  }
}

template <class E>
void expectThrowsAs(grpc::StatusCode code) {
  try {
    cast::throwIfError(grpc::Status(code, "boom"));
    FAIL() << "no exception for " << cast::statusCodeName(code);
  } catch (const E& e) {
    EXPECT_NE(std::string(e.what()).find("boom"), std::string::npos);
  } catch (const std::exception& e) {
    FAIL() << "wrong exception type for " << cast::statusCodeName(code) << ": " << e.what();
  }
}

TEST(Errors, ThrowIfErrorThrowsTheMostDerivedType) {
  expectThrowsAs<cast::AlreadyExistsError>(grpc::StatusCode::ALREADY_EXISTS);
  expectThrowsAs<cast::NotFoundError>(grpc::StatusCode::NOT_FOUND);
  expectThrowsAs<cast::ConsistencyError>(grpc::StatusCode::ABORTED);
  expectThrowsAs<cast::PermissionDeniedError>(grpc::StatusCode::PERMISSION_DENIED);
  expectThrowsAs<cast::LockedError>(grpc::StatusCode::FAILED_PRECONDITION);
  expectThrowsAs<cast::InvalidArgumentError>(grpc::StatusCode::INVALID_ARGUMENT);
  expectThrowsAs<cast::UnauthenticatedError>(grpc::StatusCode::UNAUTHENTICATED);
  expectThrowsAs<cast::DeadlineExceededError>(grpc::StatusCode::DEADLINE_EXCEEDED);
  expectThrowsAs<cast::HistoryExpiredError>(grpc::StatusCode::OUT_OF_RANGE);
  expectThrowsAs<cast::ResourceExhaustedError>(grpc::StatusCode::RESOURCE_EXHAUSTED);
  expectThrowsAs<cast::UnavailableError>(grpc::StatusCode::UNAVAILABLE);
  expectThrowsAs<cast::InternalError>(grpc::StatusCode::INTERNAL);
}

TEST(Errors, EveryNamedErrorIsACastError) {
  for (const auto& c : kCases) {
    auto err = cast::errorForCode(c.codeName, "m");
    try {
      err->raise();
    } catch (const CastError& e) {
      EXPECT_STREQ(e.name(), c.className);
      continue;
    }
    FAIL() << c.className << " is not caught as CastError";
  }
}

TEST(Errors, OtherCodesArePlainCastErrorsKeepingTheirCode) {
  auto err = cast::errorForStatus(grpc::Status(grpc::StatusCode::UNIMPLEMENTED, "no such method"));
  EXPECT_STREQ(err->name(), "CastError");
  EXPECT_EQ(err->code(), "UNIMPLEMENTED");
  EXPECT_EQ(err->message(), "no such method");
  EXPECT_THROW(err->raise(), CastError);
  EXPECT_EQ(cast::errorForCode("SOMETHING_NEW", "x")->code(), "SOMETHING_NEW");
}

TEST(Errors, UnavailableSaysTheServerIsUnreachable) {
  auto err = cast::errorForStatus(grpc::Status(grpc::StatusCode::UNAVAILABLE, "failed to connect"));
  EXPECT_EQ(err->message(),
            "server unavailable (failed to connect): a write made by this call may or may not have been applied; "
            "the client reconnects by itself, retry the call later");
}

TEST(Errors, EmptyDetailsFallBackToTheCodeName) {
  auto err = cast::errorForStatus(grpc::Status(grpc::StatusCode::NOT_FOUND, ""));
  EXPECT_EQ(err->message(), "NOT_FOUND");
}

TEST(Errors, OkStatusDoesNotThrow) { EXPECT_NO_THROW(cast::throwIfError(grpc::Status::OK)); }

// The server names the precise class of a FAILED_PRECONDITION in the
// "cast-error" trailer; the client raises it, and it is still a LockedError.
template <class E>
void expectPrecise(const char* name) {
  auto err = cast::errorForStatus(grpc::Status(grpc::StatusCode::FAILED_PRECONDITION, "task t is waiting"), name);
  EXPECT_STREQ(err->name(), name);
  EXPECT_EQ(err->code(), "FAILED_PRECONDITION");
  EXPECT_EQ(err->message(), "task t is waiting");
  EXPECT_THROW(err->raise(), E);
  EXPECT_THROW(err->raise(), cast::LockedError);
}

TEST(Errors, TheTrailerNamesAPreciseLockedError) {
  EXPECT_STREQ(cast::kErrorTrailer, "cast-error");
  expectPrecise<cast::TaskStateError>("TaskStateError");
  expectPrecise<cast::NoSessionError>("NoSessionError");
  expectPrecise<cast::SchemaConflictError>("SchemaConflictError");
  EXPECT_THROW(cast::throwIfError(grpc::Status(grpc::StatusCode::FAILED_PRECONDITION, "x"), "TaskStateError"),
               cast::TaskStateError);
}

TEST(Errors, WithoutATrailerItIsALockedError) {
  auto err = cast::errorForStatus(grpc::Status(grpc::StatusCode::FAILED_PRECONDITION, "held by b"));
  EXPECT_STREQ(err->name(), "LockedError");
  EXPECT_STREQ(cast::errorForCode("FAILED_PRECONDITION", "m", "")->name(), "LockedError");
}

TEST(Errors, AnUnknownNameInTheTrailerIsIgnored) {
  auto err = cast::errorForStatus(grpc::Status(grpc::StatusCode::FAILED_PRECONDITION, "m"), "FutureError");
  EXPECT_STREQ(err->name(), "LockedError");
  // Only the classes the trailer may name: not the plain ones, nor the base.
  EXPECT_STREQ(cast::errorForCode("FAILED_PRECONDITION", "m", "NotFoundError")->name(), "LockedError");
  EXPECT_STREQ(cast::errorForCode("FAILED_PRECONDITION", "m", "CastError")->name(), "LockedError");
}

TEST(Errors, ANameOfAnotherCodeIsIgnored) {
  auto err = cast::errorForStatus(grpc::Status(grpc::StatusCode::NOT_FOUND, "no task t"), "TaskStateError");
  EXPECT_STREQ(err->name(), "NotFoundError");
  EXPECT_EQ(err->message(), "no task t");
  EXPECT_STREQ(cast::errorForCode("SOMETHING_NEW", "m", "TaskStateError")->name(), "CastError");
}

TEST(Errors, TheTrailerIsReadFromTheTrailingMetadata) {
  const std::string value = "TaskStateError";
  std::multimap<grpc::string_ref, grpc::string_ref> trailers;
  EXPECT_EQ(cast::errorTrailer(trailers), "") << "no trailer";
  trailers.emplace("other-key", "x");
  EXPECT_EQ(cast::errorTrailer(trailers), "");
  trailers.emplace("cast-error", grpc::string_ref(value.data(), value.size()));
  EXPECT_EQ(cast::errorTrailer(trailers), "TaskStateError");
}

TEST(Errors, StatusCodeNames) {
  EXPECT_EQ(cast::statusCodeName(0), "OK");
  EXPECT_EQ(cast::statusCodeName(16), "UNAUTHENTICATED");
  EXPECT_EQ(cast::statusCodeName(99), "UNKNOWN");
  EXPECT_EQ(cast::statusCodeName(-1), "UNKNOWN");
}

}  // namespace
