// Loans (cast/loan.h) against the in-memory transport, which has no shared
// memory: a loan is private memory, its value is the message with the
// loaned field's bytes last, its type registered as a write's; the writes
// spend it. The real path, staging area and server included:
// tests/server/loan_test.cc.
#include <gtest/gtest.h>

#include <cstddef>
#include <string>

#include "bound_component.h"
#include "cast/loan.h"
#include "cast_testing.pb.h"

namespace {

using cast::testing::Bound;
using Frame = cast::testing::Frame;

void fillWith(const cast::Loan& loan, char c) {
  for (std::byte& b : loan.buffer()) b = static_cast<std::byte>(c);
}

TEST(Loan, WithoutSharedMemoryALoanIsPrivateAndItsValueIsTheMessageWithItsBytes) {
  Bound b;
  Frame frame;
  frame.set_width(4);
  frame.set_encoding("rgb8");
  frame.add_parts("p");
  cast::Loan loan = b.component.loan(frame, "pixels", 5);
  EXPECT_FALSE(loan.shared());
  EXPECT_EQ(loan.size(), 5u);
  EXPECT_EQ(b.transport->calls["loan"], 1);
  ASSERT_EQ(b.transport->registered.size(), 1u);  // the type registered with the loan, as a write registers it
  fillWith(loan, 'x');
  b.component.add("f", std::move(loan));
  Frame want = frame;
  want.set_pixels("xxxxx");
  const Frame got = b.component.get<Frame>("f");
  EXPECT_EQ(got.SerializeAsString(), want.SerializeAsString());
  EXPECT_EQ(b.transport->get("vision", "f").type, "cast.testing.Frame");
  EXPECT_TRUE(loan.buffer().empty());
  EXPECT_THROW(b.component.overwrite("f", std::move(loan)), cast::InvalidArgumentError);
  EXPECT_EQ(b.transport->registered.size(), 1u);
}

TEST(Loan, AsyncWritesAndAnEmptyFieldWork) {
  Bound b;
  cast::Loan loan = b.component.loan(Frame(), "pixels", 0);
  EXPECT_TRUE(loan.buffer().empty());
  EXPECT_EQ(b.component.addAsync("f", std::move(loan)).get().version, 0u);
  cast::Loan next = b.component.loan(Frame(), "pixels", 3);
  fillWith(next, 'y');
  b.component.overwriteAsync("f", std::move(next)).get();
  EXPECT_EQ(b.component.get<Frame>("f").pixels(), "yyy");
  EXPECT_THROW(b.component.addAsync("g", std::move(next)), cast::InvalidArgumentError);
  EXPECT_FALSE(b.transport->exists("vision", "g"));
}

TEST(Loan, AMoveLeavesAClosedLoanAndTheBufferIsASpan) {
  Bound b;
  cast::Loan loan = b.component.loan(Frame(), "pixels", 8);
  cast::Loan moved = std::move(loan);
  EXPECT_TRUE(loan.buffer().empty());  // NOLINT(bugprone-use-after-move): a moved-from loan is a closed one
  EXPECT_EQ(loan.size(), 0u);
  EXPECT_THROW(b.component.add("f", std::move(loan)), cast::InvalidArgumentError);
  cast::MutableByteSpan buffer = moved.buffer();
  ASSERT_EQ(buffer.size(), 8u);
  buffer.subspan(2, 3)[0] = std::byte{'z'};
  const cast::ByteSpan read = buffer;  // the same bytes, read-only
  EXPECT_EQ(read.data(), buffer.data());
  EXPECT_EQ(static_cast<char>(read[2]), 'z');
  EXPECT_EQ(buffer.subspan(6).size(), 2u);
  EXPECT_THROW(buffer.subspan(9), std::out_of_range);
}

}  // namespace
