// Loans (cast/loan.h) against the repository's Python server on this host: a
// large value written in place. A cast.testing.Frame whose pixels are filled
// through the loan's buffer is written from the session's staging area with
// no copy (the buffer is the staging area at the place the write names, the
// request carries no value bytes) and read back identical by a get and by a
// watcher lent it by shared memory; with shared memory off, or under the
// threshold, the buffer is private memory and readers get the same value; bad
// loans and bad writes of them are refused by name and write nothing; a
// loan closed unwritten gives its region back; a loan is written once, by an
// async write too; a loan whose session ended is still written (as bytes).
#include <gtest/gtest.h>

#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <future>
#include <limits>
#include <memory>
#include <mutex>
#include <string>
#include <utility>
#include <vector>

#include "cast/cast.h"
#include "cast_server.h"
#include "cast_testing.pb.h"
#include "loan_state.h"
#include "shm_session.h"
#include "transport.h"

namespace {

using namespace std::chrono_literals;
using cast::detail::ClientSession;
using cast::detail::LoanAccess;
using cast::detail::LoanState;
using cast::testing::CastServer;
using cast::testing::eventually;
using cast::testing::kMiB;
using cast::testing::sharedServer;
using Frame = cast::testing::Frame;

// A component of "vision" and its transport, whose shared-memory session the
// test looks at (Transport::sharedSession).
struct Writer {
  Writer(const CastServer& server, const std::string& id)
      : transport(cast::connectGrpc(server.endpoint(), server.token(id, "vision"), cast::Identity{id, "vision", false},
                                    cast::TransportOptions{})),
        component(cast::connect(transport)) {}
  std::shared_ptr<ClientSession> session() const { return transport->sharedSession("vision"); }

  std::shared_ptr<cast::detail::Transport> transport;
  std::unique_ptr<cast::Connection> component;
};

// A frame's every field but its pixels.
Frame frameWithoutPixels(std::size_t size) {
  Frame f;
  f.set_width(static_cast<std::uint32_t>(size / 1024));
  f.set_height(1024);
  f.set_encoding("mono8");
  return f;
}

// Pixels of `size` bytes that differ from one `seed` to the next.
std::string pixels(std::size_t size, int seed) {
  std::string out(size, '\0');
  for (std::size_t i = 0; i < size; ++i) out[i] = static_cast<char>((seed * 7 + i) % 251);
  return out;
}

// The frame a loan of `size` pixels filled with `seed` makes.
Frame expectedFrame(std::size_t size, int seed) {
  Frame f = frameWithoutPixels(size);
  f.set_pixels(pixels(size, seed));
  return f;
}

// Fills a loan's buffer with the pixels of `seed`, in place.
void fill(const cast::Loan& loan, int seed) {
  cast::MutableByteSpan buffer = loan.buffer();
  for (std::size_t i = 0; i < buffer.size(); ++i) buffer[i] = static_cast<std::byte>((seed * 7 + i) % 251);
}

// Whether two frames are the same, every byte.
bool same(const Frame& a, const Frame& b) { return a.SerializeAsString() == b.SerializeAsString(); }

TEST(Loans, AFrameFilledInPlaceIsWrittenSharedAndReadIdenticalByAGetAndByAWatcher) {
  Writer writer(sharedServer(), "loan-writer");
  auto watcher = sharedServer().connect("loan-watcher", "vision");
  struct Seen {
    bool shared;
    bool right;  // the frame decoded and the view's pixels are the frame written, every byte
  };
  std::mutex mu;
  std::vector<Seen> seen;
  std::vector<Frame> written = {expectedFrame(kMiB, 1), expectedFrame(kMiB, 2)};
  watcher->onChange(cast::addressFilter("loan-frame").withEntry(), [&](const cast::WorkingMemoryChange& change) {
    cast::ValueView view = change.view();
    std::lock_guard<std::mutex> lock(mu);
    const Frame& want = written[seen.size() % 2];
    seen.push_back({view.shared(), same(change.entry<Frame>().value, want) && view.field(4).chars() == want.pixels()});
  });
  cast::Connection& c = *writer.component;

  cast::Loan loan = c.loan(frameWithoutPixels(kMiB), "pixels", kMiB);
  EXPECT_TRUE(loan.shared());
  EXPECT_EQ(loan.size(), kMiB);
  ASSERT_EQ(loan.buffer().size(), kMiB);
  // The pixels start on a 64-byte line, so an array over them is aligned.
  EXPECT_EQ(reinterpret_cast<std::uintptr_t>(loan.buffer().data()) % 64, 0u);
  fill(loan, 1);
  const cast::WriteResult added = c.add("loan-frame", std::move(loan));
  EXPECT_TRUE(same(c.get<Frame>("loan-frame"), written[0]));

  cast::Loan next = c.loan(frameWithoutPixels(kMiB), "pixels", kMiB);
  EXPECT_TRUE(next.shared());
  fill(next, 2);
  EXPECT_EQ(c.overwrite("loan-frame", std::move(next), "", added.version).version, added.version + 1);
  const cast::Entry<Frame> entry = watcher->getEntry<Frame>("loan-frame");
  EXPECT_TRUE(same(entry.value, written[1]));
  EXPECT_EQ(entry.author, "loan-writer");
  EXPECT_EQ(watcher->getView("loan-frame").type(), "cast.testing.Frame");
  ASSERT_TRUE(eventually([&] {
    std::lock_guard<std::mutex> lock(mu);
    return seen.size() == 2;
  }));
  for (std::size_t i = 0; i < 2; ++i) {
    EXPECT_TRUE(seen[i].shared) << "change " << i << " came as bytes";
    EXPECT_TRUE(seen[i].right) << "change " << i;
  }
}

TEST(Loans, ALoanIsWrittenFromTheStagingAreaWhereItWasFilledWithNoCopy) {
  Writer writer(sharedServer(), "loan-in-place");
  cast::Connection& c = *writer.component;
  const std::shared_ptr<ClientSession> session = writer.session();
  ASSERT_TRUE(session);
  const std::shared_ptr<const cast::detail::Mapping> staging = session->stagingArea();
  ASSERT_TRUE(staging);

  cast::Loan loan = c.loan(frameWithoutPixels(kMiB), "pixels", kMiB);
  ASSERT_TRUE(loan.shared());
  LoanState* state = LoanAccess::state(loan);
  ASSERT_NE(state, nullptr);
  EXPECT_EQ(state->session(), session);
  ASSERT_TRUE(state->region());
  const cast::detail::Staged region = *state->region();
  // The buffer is the session's staging area, right after the header, the payload on a 64-byte line there.
  EXPECT_EQ(reinterpret_cast<const char*>(loan.buffer().data()),
            staging->data() + region.offset + state->headerSize());
  EXPECT_EQ((region.offset + state->headerSize()) % 64, 0u);
  EXPECT_LT(region.pad, 64u);
  EXPECT_EQ(region.size, state->headerSize() + kMiB);
  fill(loan, 3);
  // What is at that place is the whole value, serialised: the server reads it as it is.
  Frame there;
  ASSERT_TRUE(there.ParseFromArray(staging->data() + region.offset, static_cast<int>(region.size)));
  EXPECT_TRUE(same(there, expectedFrame(kMiB, 3)));

  const auto before = cast::testing::sharedMemoryFigures(sharedServer());
  const std::uint64_t sentBefore = session->writes().sentBytes();
  c.add("loan-in-place", std::move(loan));
  const auto after = cast::testing::sharedMemoryFigures(sharedServer());
  // The write named the loan's region, and the request carried no bytes of the value.
  EXPECT_TRUE(state->writtenInPlace());
  EXPECT_EQ(after.staged_writes() - before.staged_writes(), 1u);
  EXPECT_EQ(after.staged_bytes() - before.staged_bytes(), region.size);
  EXPECT_EQ(writer.session(), session);
  EXPECT_LT(session->writes().sentBytes() - sentBefore, 512u);
  EXPECT_TRUE(same(c.get<Frame>("loan-in-place"), expectedFrame(kMiB, 3)));
  // The region went back with the reply.
  EXPECT_EQ(session->stagingUsed(), 0u);
  EXPECT_TRUE(loan.buffer().empty());  // spent
}

TEST(Loans, WithSharedMemoryOffALoanIsPrivateMemoryAndReadersGetTheSameValue) {
  auto watcher = sharedServer().connect("loan-far-watcher", "vision");
  std::mutex mu;
  std::vector<std::pair<bool, bool>> seen;  // (shared, right)
  watcher->onChange(cast::addressFilter("loan-far").withEntry(), [&](const cast::WorkingMemoryChange& change) {
    const bool right = same(change.entry<Frame>().value, expectedFrame(kMiB, 4));
    std::lock_guard<std::mutex> lock(mu);
    seen.emplace_back(change.view().shared(), right);
  });
  ::setenv("CAST_SHARED_MEMORY", "off", 1);
  Writer writer(sharedServer(), "loan-far-writer");
  ::unsetenv("CAST_SHARED_MEMORY");
  cast::Connection& c = *writer.component;
  EXPECT_FALSE(writer.session());

  const auto before = cast::testing::sharedMemoryFigures(sharedServer());
  cast::Loan loan = c.loan(frameWithoutPixels(kMiB), "pixels", kMiB);
  EXPECT_FALSE(loan.shared());
  EXPECT_EQ(loan.size(), kMiB);
  ASSERT_EQ(loan.buffer().size(), kMiB);
  EXPECT_FALSE(LoanAccess::state(loan)->region());
  fill(loan, 4);
  c.add("loan-far", std::move(loan));
  EXPECT_EQ(cast::testing::sharedMemoryFigures(sharedServer()).staged_writes(), before.staged_writes());  // bytes
  EXPECT_TRUE(same(watcher->get<Frame>("loan-far"), expectedFrame(kMiB, 4)));
  EXPECT_TRUE(same(c.get<Frame>("loan-far"), expectedFrame(kMiB, 4)));
  ASSERT_TRUE(eventually([&] {
    std::lock_guard<std::mutex> lock(mu);
    return !seen.empty();
  }));
  EXPECT_TRUE(seen[0].first);  // the watcher on the host is lent it all the same
  EXPECT_TRUE(seen[0].second);
}

TEST(Loans, ASmallLoanIsPrivateMemoryAndItsValueIsRight) {
  Writer writer(sharedServer(), "loan-small");
  cast::Connection& c = *writer.component;
  ASSERT_TRUE(writer.session());
  cast::Loan loan = c.loan(frameWithoutPixels(1000), "pixels", 1000);
  EXPECT_FALSE(loan.shared());  // under the session's threshold
  EXPECT_EQ(writer.session()->stagingUsed(), 0u);
  fill(loan, 5);
  c.add("loan-small", std::move(loan));
  EXPECT_TRUE(same(c.get<Frame>("loan-small"), expectedFrame(1000, 5)));
  cast::ValueView view = c.getView("loan-small");
  EXPECT_FALSE(view.shared());
  EXPECT_TRUE(view.field(4).chars() == pixels(1000, 5));
}

// The InvalidArgumentError `call` throws ("" if it throws none).
template <class Call>
std::string refusal(Call&& call) {
  try {
    call();
  } catch (const cast::InvalidArgumentError& e) {
    return e.message();
  }
  return "";
}

TEST(Loans, EveryBadLoanAndEveryBadWriteOfOneIsRefusedByNameAndWritesNothing) {
  Writer writer(sharedServer(), "loan-bad");
  cast::Connection& c = *writer.component;
  const std::shared_ptr<ClientSession> session = writer.session();
  ASSERT_TRUE(session);
  const Frame frame = frameWithoutPixels(kMiB);
  EXPECT_EQ(refusal([&] { c.loan(frame, "pixel", kMiB); }),
            "Frame has no field 'pixel': a loan is taken of one of its top-level bytes fields (pixels)");
  EXPECT_EQ(refusal([&] { c.loan(frame, "width", kMiB); }),
            "field 'width' of cast.testing.Frame is a uint32: a loan is taken of a top-level singular bytes field");
  EXPECT_EQ(refusal([&] { c.loan(frame, "parts", kMiB); }),
            "field 'parts' of cast.testing.Frame is a repeated bytes: a loan is taken of a top-level singular bytes "
            "field");
  cast::testing::Pose pose;
  EXPECT_EQ(refusal([&] { c.loan(pose, "tags", kMiB); }),
            "field 'tags' of cast.testing.Pose is a repeated string: a loan is taken of a top-level singular bytes "
            "field");
  EXPECT_EQ(refusal([&] { c.loan(pose, "pixels", kMiB); }),
            "Pose has no field 'pixels': a loan is taken of one of its top-level bytes fields (it has none)");
  Frame holding = frame;
  holding.set_pixels("abc");
  EXPECT_EQ(refusal([&] { c.loan(holding, "pixels", kMiB); }),
            "field 'pixels' of cast.testing.Frame already holds 3 bytes: leave it empty, the loan's buffer is its "
            "bytes");
  EXPECT_NE(refusal([&] { c.loan(frame, "pixels", std::numeric_limits<std::size_t>::max()); }).find("2 GiB"),
            std::string::npos);
  EXPECT_EQ(session->stagingUsed(), 0u);  // nothing reserved

  // Written to another SA than the one it was taken for (both resolved: "" is "vision"): refused, the loan untouched.
  cast::Loan loan = c.loan(frame, "pixels", kMiB);
  ASSERT_TRUE(loan.shared());
  fill(loan, 6);
  EXPECT_EQ(refusal([&] { c.add("loan-bad", std::move(loan), "language"); }),
            "the loan was taken for subarchitecture 'vision' and is written to 'language': take it with "
            "subarchitecture 'language'");
  EXPECT_EQ(refusal([&] { c.overwriteAsync("loan-bad", std::move(loan), "language"); }),
            "the loan was taken for subarchitecture 'vision' and is written to 'language': take it with "
            "subarchitecture 'language'");
  cast::Loan other = c.loan(frameWithoutPixels(1000), "pixels", 1000, "language");
  EXPECT_EQ(refusal([&] { c.add("loan-bad", std::move(other)); }),
            "the loan was taken for subarchitecture 'language' and is written to 'vision': take it with "
            "subarchitecture 'vision'");
  EXPECT_FALSE(c.exists("loan-bad"));
  EXPECT_FALSE(c.exists("loan-bad", "language"));
  EXPECT_EQ(loan.buffer().size(), kMiB);  // still the loan's, and still written where it was taken for
  const std::uint64_t version = c.add("loan-bad", std::move(loan), "vision").version;
  EXPECT_TRUE(same(c.get<Frame>("loan-bad"), expectedFrame(kMiB, 6)));

  // A closed loan is not written.
  cast::Loan closed = c.loan(frame, "pixels", kMiB);
  closed.close();
  EXPECT_EQ(refusal([&] { c.overwrite("loan-bad", std::move(closed)); }),
            "this loan was already written (or closed): take a new loan for each write");
  cast::Loan none;
  EXPECT_EQ(refusal([&] { c.add("loan-none", std::move(none)); }),
            "this loan was already written (or closed): take a new loan for each write");
  EXPECT_FALSE(c.exists("loan-none"));
  EXPECT_EQ(c.getEntry<Frame>("loan-bad").version, version);
  EXPECT_EQ(session->stagingUsed(), 0u);
}

TEST(Loans, ALoanClosedUnwrittenGivesItsRegionBack) {
  Writer writer(sharedServer(), "loan-back");
  cast::Connection& c = *writer.component;
  const std::shared_ptr<ClientSession> session = writer.session();
  ASSERT_TRUE(session);
  // Each more than half of the staging area (2 x limits.max_value_bytes): two never fit at once.
  const std::size_t size = session->stagingBytes() / 2 + 1;
  const Frame frame = frameWithoutPixels(size);
  cast::Loan first = c.loan(frame, "pixels", size);
  ASSERT_TRUE(first.shared());
  {
    cast::Loan second = c.loan(frame, "pixels", size);
    EXPECT_FALSE(second.shared());  // no room while the first holds its region
  }
  first.close();
  first.close();  // closing a closed loan does nothing
  EXPECT_TRUE(first.buffer().empty());
  EXPECT_EQ(session->stagingUsed(), 0u);
  {
    cast::Loan second = c.loan(frame, "pixels", size);
    EXPECT_TRUE(second.shared());  // the first's region came back
  }  // destroyed unwritten: its region comes back too
  EXPECT_EQ(session->stagingUsed(), 0u);
  cast::Loan third = c.loan(frame, "pixels", size);
  EXPECT_TRUE(third.shared());
  third = cast::Loan();  // a loan replaced by assignment is closed
  EXPECT_EQ(session->stagingUsed(), 0u);
  cast::Loan fourth = c.loan(frame, "pixels", size);
  EXPECT_TRUE(fourth.shared());
}

TEST(Loans, ALoanIsWrittenOnce) {
  Writer writer(sharedServer(), "loan-once");
  cast::Connection& c = *writer.component;
  cast::Loan loan = c.loan(frameWithoutPixels(kMiB), "pixels", kMiB);
  ASSERT_TRUE(loan.shared());
  fill(loan, 7);
  const std::uint64_t version = c.add("loan-once", std::move(loan)).version;
  EXPECT_TRUE(loan.buffer().empty());  // spent: its buffer is gone
  EXPECT_EQ(refusal([&] { c.overwrite("loan-once", std::move(loan)); }),
            "this loan was already written (or closed): take a new loan for each write");
  EXPECT_EQ(refusal([&] { c.addAsync("loan-twice", std::move(loan)); }),
            "this loan was already written (or closed): take a new loan for each write");
  loan.close();  // closing a written loan does nothing
  const cast::Entry<Frame> entry = c.getEntry<Frame>("loan-once");
  EXPECT_EQ(entry.version, version);
  EXPECT_TRUE(same(entry.value, expectedFrame(kMiB, 7)));
  EXPECT_FALSE(c.exists("loan-twice"));
  // A failed write spends its loan too, and gives its region back.
  cast::Loan again = c.loan(frameWithoutPixels(kMiB), "pixels", kMiB);
  EXPECT_THROW(c.add("loan-once", std::move(again)), cast::AlreadyExistsError);
  EXPECT_EQ(refusal([&] { c.overwrite("loan-once", std::move(again)); }),
            "this loan was already written (or closed): take a new loan for each write");
  EXPECT_EQ(writer.session()->stagingUsed(), 0u);
  EXPECT_EQ(c.getEntry<Frame>("loan-once").version, version);
}

TEST(Loans, AnAsyncWriteOfALoanWorksAndSpendsIt) {
  Writer writer(sharedServer(), "loan-async");
  cast::Connection& c = *writer.component;
  cast::Loan first = c.loan(frameWithoutPixels(kMiB), "pixels", kMiB);
  ASSERT_TRUE(first.shared());
  fill(first, 8);
  std::future<cast::WriteResult> added = c.addAsync("loan-async", std::move(first));
  EXPECT_TRUE(first.buffer().empty());  // spent at once
  EXPECT_EQ(refusal([&] { c.overwriteAsync("loan-async", std::move(first)); }),
            "this loan was already written (or closed): take a new loan for each write");
  std::vector<std::future<cast::WriteResult>> overwrites;
  for (int seed = 9; seed < 12; ++seed) {
    cast::Loan loan = c.loan(frameWithoutPixels(kMiB), "pixels", kMiB);
    fill(loan, seed);
    LoanState* state = LoanAccess::state(loan);
    const bool shared = loan.shared();
    overwrites.push_back(c.overwriteAsync("loan-async", std::move(loan)));
    EXPECT_EQ(state->writtenInPlace(), shared);
    EXPECT_TRUE(state->spent());
  }
  std::uint64_t version = added.get().version;
  for (auto& f : overwrites) EXPECT_EQ(f.get().version, ++version);
  EXPECT_TRUE(same(c.get<Frame>("loan-async"), expectedFrame(kMiB, 11)));
  EXPECT_TRUE(eventually([&] { return writer.session()->stagingUsed() == 0; }));
}

TEST(Loans, ALoanWhoseSessionEndedKeepsItsBufferAndIsWrittenAsBytes) {
  Writer writer(sharedServer(), "loan-orphan");
  cast::Connection& c = *writer.component;
  std::shared_ptr<ClientSession> session = writer.session();
  ASSERT_TRUE(session);
  cast::Loan loan = c.loan(frameWithoutPixels(kMiB), "pixels", kMiB);
  ASSERT_TRUE(loan.shared());
  session->close();  // as when the server ends it: the staging area stays mapped for the loan
  session.reset();
  fill(loan, 12);  // the buffer is still there to write
  c.add("loan-orphan", std::move(loan));
  EXPECT_FALSE(LoanAccess::state(loan)->writtenInPlace());  // its session is not the one the write went on
  EXPECT_TRUE(same(c.get<Frame>("loan-orphan"), expectedFrame(kMiB, 12)));
}

}  // namespace
