// The client's side of large values by shared memory, below the transport
// (src/shm_wire.cc, src/shm_session.cc, src/shm.cc): frames byte by byte,
// the staging area's regions, and a session whose other end is this test,
// playing the server's part of the frames (the end to end path against the
// real server is tests/server/shared_memory_test.cc).
#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "shm.h"
#include "shm_session.h"
#include "shm_wire.h"

namespace {

using cast::detail::ClientSession;
using cast::detail::Extents;
using cast::detail::Staged;
namespace shm = cast::detail::shm;

std::string le(std::uint64_t v, int bytes) {
  std::string out;
  for (int i = 0; i < bytes; ++i) out.push_back(static_cast<char>((v >> (8 * i)) & 0xff));
  return out;
}

std::string repeat(const std::string& unit, int times) {
  std::string out;
  for (int i = 0; i < times; ++i) out += unit;
  return out;
}

std::string frame(std::uint8_t kind, const std::string& body) {
  return le(body.size() + 1, 4) + std::string(1, static_cast<char>(kind)) + body;
}

// A memory file of `size` bytes holding `fill`, sealed as the server seals
// its segments (nobody can write it again but through this mapping, gone here).
int sealedFile(const std::string& fill, std::size_t size) {
  const int fd = ::memfd_create("cast-test-segment", MFD_CLOEXEC | MFD_ALLOW_SEALING);
  EXPECT_GE(fd, 0);
  EXPECT_EQ(::ftruncate(fd, static_cast<off_t>(size)), 0);
  EXPECT_EQ(::pwrite(fd, fill.data(), fill.size(), 0), static_cast<ssize_t>(fill.size()));
#ifndef F_SEAL_FUTURE_WRITE
#define F_SEAL_FUTURE_WRITE 0x0010
#endif
  EXPECT_EQ(::fcntl(fd, F_ADD_SEALS, F_SEAL_FUTURE_WRITE | F_SEAL_GROW | F_SEAL_SHRINK | F_SEAL_SEAL), 0);
  return fd;
}

// Sends `bytes` with `fd` as SCM_RIGHTS (-1: none).
void sendWith(int socket, const std::string& bytes, int fd) {
  iovec iov{const_cast<char*>(bytes.data()), bytes.size()};
  msghdr msg{};
  msg.msg_iov = &iov;
  msg.msg_iovlen = 1;
  alignas(cmsghdr) char control[CMSG_SPACE(sizeof(int))];
  if (fd >= 0) {
    msg.msg_control = control;
    msg.msg_controllen = sizeof control;
    cmsghdr* c = CMSG_FIRSTHDR(&msg);
    c->cmsg_level = SOL_SOCKET;
    c->cmsg_type = SCM_RIGHTS;
    c->cmsg_len = CMSG_LEN(sizeof(int));
    std::memcpy(CMSG_DATA(c), &fd, sizeof(int));
  }
  ASSERT_EQ(::sendmsg(socket, &msg, 0), static_cast<ssize_t>(bytes.size()));
}

// The frames the client sent so far (waiting up to a second for the first).
std::vector<shm::Frame> framesFrom(int socket, shm::FrameReader& reader) {
  std::vector<shm::Frame> out;
  shm::Inbox inbox;
  for (int i = 0; i < 100 && out.empty(); ++i) {
    auto fds = inbox.receive(socket);
    if (!fds) {
      ::usleep(10000);
      continue;
    }
    if (inbox.size() == 0) break;
    out = reader.feed(inbox.data(), inbox.size(), *fds);
  }
  return out;
}

// A reference to `size` bytes at `offset` of segment `segment`, lent as value `valueId`.
cast::v1::SharedValue reference(std::uint32_t segment, std::uint64_t offset, std::uint64_t size,
                                std::uint64_t valueId = 0) {
  cast::v1::SharedValue ref;
  ref.set_segment(segment);
  ref.set_offset(offset);
  ref.set_size(size);
  ref.set_value_id(valueId);
  return ref;
}

// A session over a socket pair: the test holds the server's end.
struct Pair {
  Pair() {
    int fds[2];
    EXPECT_EQ(::socketpair(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0, fds), 0);
    server = fds[1];
    ::fcntl(server, F_SETFL, O_NONBLOCK);
    staging = ::memfd_create("cast-test-staging", MFD_CLOEXEC);
    EXPECT_EQ(::ftruncate(staging, kStaging), 0);
    const int stagingCopy = ::dup(staging);  // the session closes the one it is given
    shm::Welcome w;
    w.version = 1;
    w.session = std::string(16, '\x01');
    w.serverId = std::string(16, '\x02');
    w.threshold = 1024;
    w.window = 1 << 20;
    w.staging = kStaging;
    session = std::make_shared<ClientSession>(fds[0], w, stagingCopy, "test:1");
  }
  ~Pair() {
    session.reset();
    ::close(server);
    ::close(staging);
  }
  // Maps segment `id` of `size` bytes holding `fill` into the session, as the
  // server's SEGMENT frame does.
  void offerSegment(std::uint32_t id, const std::string& fill, std::size_t size) {
    const int segment = sealedFile(fill, size);
    sendWith(server, frame(shm::kSegment, le(id, 4) + le(size, 8)), segment);
    ::close(segment);
  }
  static constexpr std::size_t kStaging = 64 * 1024;
  int server = -1;
  int staging = -1;
  std::shared_ptr<ClientSession> session;
  shm::FrameReader reader;
};

// ------------------------------------------------------------------ frames

TEST(SharedMemoryFrames, AreLittleEndianLengthKindAndFields) {
  EXPECT_EQ(shm::hello("tok"), le(6, 4) + "\x01" + le(1, 2) + "tok");
  EXPECT_EQ(shm::release({7, 1ull << 40}), le(17, 4) + "\x02" + le(7, 8) + le(1ull << 40, 8));
  EXPECT_EQ(shm::received(3, 64, true), le(18, 4) + "\x03" + le(3, 8) + le(64, 8) + "\x01");
  EXPECT_EQ(shm::received(3, 5, false).back(), '\0');
  const std::string body = le(1, 2) + std::string(16, 'S') + std::string(16, '\xab') + le(65536, 8) + le(1 << 26, 8) +
                           le(1 << 24, 8);
  const shm::Welcome w = shm::parseWelcome(body);
  EXPECT_EQ(w.session, std::string(16, 'S'));
  EXPECT_EQ(shm::hex(w.serverId), repeat("ab", 16));
  EXPECT_EQ(w.threshold, 65536u);
  EXPECT_EQ(w.window, 1u << 26);
  EXPECT_EQ(w.staging, 1u << 24);
  EXPECT_THROW(shm::parseWelcome(body + "x"), shm::ProtocolError);
  EXPECT_EQ(shm::parseSegment(le(9, 4) + le(4096, 8)), std::make_pair(9u, std::uint64_t{4096}));
  EXPECT_EQ(shm::parseRetire(le(9, 4)), 9u);
  EXPECT_THROW(shm::parseRetire(le(9, 8)), shm::ProtocolError);
}

TEST(SharedMemoryFrames, AReaderSplitsFramesAndGivesEachItsDescriptorInOrder) {
  shm::FrameReader reader;
  const std::string stream = frame(shm::kSegment, le(1, 4) + le(4096, 8)) + frame(shm::kRetire, le(0, 4)) +
                             frame(shm::kSegment, le(2, 4) + le(8192, 8));
  const int a = ::memfd_create("a", MFD_CLOEXEC);
  const int b = ::memfd_create("b", MFD_CLOEXEC);
  // Both descriptors arrive with the first bytes; the frames come in pieces.
  auto first = reader.feed(stream.data(), 7, {a, b});
  EXPECT_TRUE(first.empty());
  auto rest = reader.feed(stream.data() + 7, stream.size() - 7, {});
  ASSERT_EQ(rest.size(), 3u);
  EXPECT_EQ(rest[0].fd, a);
  EXPECT_EQ(rest[1].fd, -1);
  EXPECT_EQ(rest[2].fd, b);
  EXPECT_EQ(shm::parseSegment(rest[2].body).second, 8192u);
  ::close(a);
  ::close(b);
  shm::FrameReader bad;
  const std::string empty = le(0, 4);
  EXPECT_THROW(bad.feed(empty.data(), empty.size(), {}), shm::ProtocolError);
  shm::FrameReader huge;
  const std::string big = le(shm::kMaxFrame + 1, 4) + std::string(1, static_cast<char>(shm::kSegment));
  EXPECT_THROW(huge.feed(big.data(), big.size(), {}), shm::ProtocolError);
  // REPLIES (and WRITES) may be longer, up to kMaxWritesFrame.
  shm::FrameReader long_;
  const std::string longer = le(shm::kMaxFrame + 1, 4) + std::string(1, static_cast<char>(shm::kReplies));
  EXPECT_TRUE(long_.feed(longer.data(), longer.size(), {}).empty());
  shm::FrameReader tooLong;
  const std::string over = le(shm::kMaxWritesFrame + 1, 4) + std::string(1, static_cast<char>(shm::kReplies));
  EXPECT_THROW(tooLong.feed(over.data(), over.size(), {}), shm::ProtocolError);
  // EVENTS too (a watch's batch), with its call number first.
  shm::FrameReader events;
  const std::string longEvents = le(shm::kMaxFrame + 1, 4) + std::string(1, static_cast<char>(shm::kEvents));
  EXPECT_TRUE(events.feed(longEvents.data(), longEvents.size(), {}).empty());
  shm::FrameReader eventsOver;
  const std::string overEvents = le(shm::kMaxWritesFrame + 1, 4) + std::string(1, static_cast<char>(shm::kEvents));
  EXPECT_THROW(eventsOver.feed(overEvents.data(), overEvents.size(), {}), shm::ProtocolError);
  shm::FrameReader batch;
  const std::string eventsFrame = frame(shm::kEvents, le(77, 8) + "batch");
  auto got = batch.feed(eventsFrame.data(), eventsFrame.size(), {});
  ASSERT_EQ(got.size(), 1u);
  EXPECT_EQ(shm::parseEventsCall(got[0].body), 77u);
  EXPECT_EQ(got[0].body.substr(8), "batch");
  EXPECT_THROW(shm::parseEventsCall("short"), shm::ProtocolError);
  shm::FrameReader noFd;
  const std::string segment = frame(shm::kSegment, le(1, 4) + le(4096, 8));
  EXPECT_THROW(noFd.feed(segment.data(), segment.size(), {}), shm::ProtocolError);
}

TEST(SharedMemoryFrames, ARegionOfTheStagingAreaIsTakenFirstFitAndMergedWhenGiven) {
  Extents e(10 * 4096);
  EXPECT_EQ(e.take(4096), 0u);
  EXPECT_EQ(e.take(2 * 4096), 4096u);
  EXPECT_EQ(e.take(4096), 3 * 4096u);
  EXPECT_EQ(e.take(7 * 4096), std::nullopt);
  e.give(4096, 2 * 4096);
  EXPECT_EQ(e.take(4096), 4096u);  // first fit
  e.give(0, 4096);
  e.give(4096, 4096);
  e.give(3 * 4096, 4096);
  EXPECT_EQ(e.used(), 0u);
  EXPECT_EQ(e.take(10 * 4096), 0u);  // merged back into one run
  EXPECT_EQ(cast::detail::roundUpToPages(0), 4096u);
  EXPECT_EQ(cast::detail::roundUpToPages(4097), 8192u);
}

TEST(SharedMemoryFrames, OneSettingTurnsSharedMemoryOff) {
  for (const char* off : {"off", "0", "false", "NO", " Off "}) {
    ::setenv("CAST_SHARED_MEMORY", off, 1);
    EXPECT_TRUE(cast::detail::sharedMemoryTurnedOff()) << off;
  }
  for (const char* on : {"on", "1", "", "yes"}) {
    ::setenv("CAST_SHARED_MEMORY", on, 1);
    EXPECT_FALSE(cast::detail::sharedMemoryTurnedOff()) << on;
  }
  ::unsetenv("CAST_SHARED_MEMORY");
  EXPECT_FALSE(cast::detail::sharedMemoryTurnedOff());
}

// ----------------------------------------------------------------- sessions

TEST(SharedMemorySession, StagesValuesInTheStagingAreaAndKeepsTheRegionOfAWriteInDoubt) {
  Pair p;
  const std::string value(5000, 'v');
  std::optional<Staged> a = p.session->stage(value);
  ASSERT_TRUE(a);
  EXPECT_EQ(a->offset, 0u);
  EXPECT_EQ(a->taken, 8192u);
  // The server's copy of the staging area sees the bytes.
  std::string seen(value.size(), '\0');
  ASSERT_EQ(::pread(p.staging, seen.data(), seen.size(), static_cast<off_t>(a->offset)),
            static_cast<ssize_t>(seen.size()));
  EXPECT_EQ(seen, value);
  cast::v1::StagedValue named;
  p.session->describe(*a, &named);
  EXPECT_EQ(named.session(), std::string(16, '\x01'));
  EXPECT_EQ(named.offset(), 0u);
  EXPECT_EQ(named.size(), 5000u);

  // Known outcome: the region is used again. Unknown: never again.
  p.session->unstage(*a, true);
  std::optional<Staged> b = p.session->stage(std::string(5000, 'w'));
  ASSERT_TRUE(b);
  EXPECT_EQ(b->offset, 0u);
  p.session->unstage(*b, false);
  EXPECT_EQ(p.session->quarantined(), 8192u);
  std::optional<Staged> c = p.session->stage(std::string(5000, 'x'));
  ASSERT_TRUE(c);
  EXPECT_EQ(c->offset, 8192u);
  ASSERT_EQ(::pread(p.staging, seen.data(), 1, 0), 1);
  EXPECT_EQ(seen[0], 'w');  // the write in doubt still finds its bytes
  // No room: nullopt (the value travels as bytes).
  EXPECT_FALSE(p.session->stage(std::string(Pair::kStaging, 'y')));
}

TEST(SharedMemorySession, ALoansRegionPutsItsPayloadOnA64ByteLineAndIsGivenBackWholeAndOutlivesTheSession) {
  Pair p;
  std::optional<Staged> first = p.session->stage(std::string(5000, 'v'));  // the next region starts at 8192
  ASSERT_TRUE(first);
  // A value of 5000 bytes whose payload starts after a header of 10: 54 bytes of pad put it on a line.
  std::optional<cast::detail::Reserved> loan = p.session->reserve(5000, 10);
  ASSERT_TRUE(loan);
  EXPECT_EQ(loan->staged.pad, 54u);
  EXPECT_EQ(loan->staged.offset, 8192u + 54u);
  EXPECT_EQ(loan->staged.size, 5000u);
  EXPECT_EQ(loan->staged.taken, 8192u);  // pad + size, in whole pages
  EXPECT_EQ((loan->staged.offset + 10) % cast::detail::kLoanAlignment, 0u);
  cast::v1::StagedValue named;
  p.session->describe(loan->staged, &named);
  EXPECT_EQ(named.offset(), 8192u + 54u);  // what the server is told: the header's first byte
  EXPECT_EQ(named.size(), 5000u);
  // A header of a whole number of lines needs no pad.
  std::optional<cast::detail::Reserved> lined = p.session->reserve(100, 128);
  ASSERT_TRUE(lined);
  EXPECT_EQ(lined->staged.pad, 0u);
  p.session->unstage(lined->staged, true);
  // Given back, the whole region is free again, its pad included.
  EXPECT_EQ(p.session->stagingUsed(), 16384u);
  p.session->unstage(loan->staged, true);
  EXPECT_EQ(p.session->stagingUsed(), 8192u);
  std::optional<Staged> again = p.session->stage(std::string(8192, 'w'));
  ASSERT_TRUE(again);
  EXPECT_EQ(again->offset, 8192u);
  // The mapping a loan holds stays mapped after its session ended: its buffer can still be written.
  std::optional<cast::detail::Reserved> held = p.session->reserve(100, 0);
  ASSERT_TRUE(held);
  p.session->close();
  EXPECT_FALSE(p.session->reserve(100, 0));  // an ended session places no loan
  held->staging->data()[held->staged.offset] = 'x';
  EXPECT_EQ(held->staging->data()[held->staged.offset], 'x');
  p.session.reset();
  held->staging->data()[held->staged.offset + 99] = 'y';  // the session is gone, the mapping is not
  char seen = 0;
  ASSERT_EQ(::pread(p.staging, &seen, 1, static_cast<off_t>(held->staged.offset)), 1);
  EXPECT_EQ(seen, 'x');
}

TEST(SharedMemorySession, AValueLentIsReadInPlaceAndGivenBackWhenTheLastHolderGoes) {
  Pair p;
  std::string pixels(3 * 4096, '\0');
  for (std::size_t i = 0; i < pixels.size(); ++i) pixels[i] = static_cast<char>(i % 251);
  p.offerSegment(5, pixels, 4 * 4096);

  auto call = p.session->newCall();
  EXPECT_EQ(call->metadata(), repeat("01", 16) + "/1");
  const cast::v1::SharedValue ref = reference(5, 4096, 100, 77);
  std::shared_ptr<const cast::detail::LentBytes> lent = call->claim(ref);
  EXPECT_EQ(std::string(lent->data(), lent->size()), pixels.substr(4096, 100));
  EXPECT_EQ(p.session->segments(), 1u);
  // The same value lent again on the call: a second lease.
  auto again = call->claim(ref);
  call->end(true);
  auto received = framesFrom(p.server, p.reader);
  ASSERT_EQ(received.size(), 1u);
  EXPECT_EQ(received[0].kind, shm::kReceived);
  EXPECT_EQ(received[0].body, le(1, 8) + le(2, 8) + "\x01");

  // RETIRE while held: the mapping stays until the value is let go.
  sendWith(p.server, frame(shm::kRetire, le(5, 4)), -1);
  p.session->poll(std::chrono::milliseconds(200));
  EXPECT_EQ(p.session->segments(), 0u);
  EXPECT_EQ(lent->data()[0], pixels[4096]);
  lent.reset();
  auto released = framesFrom(p.server, p.reader);
  ASSERT_EQ(released.size(), 1u);
  EXPECT_EQ(released[0].kind, shm::kRelease);
  EXPECT_EQ(released[0].body, le(77, 8));
  again.reset();
  released = framesFrom(p.server, p.reader);
  ASSERT_EQ(released.size(), 1u);
  EXPECT_EQ(released[0].body, le(77, 8));  // once per time it was lent
}

TEST(SharedMemorySession, ALongCallSaysWhatItReceivedEvery64Values) {
  Pair p;
  p.offerSegment(1, std::string(4096, 's'), 4096);
  auto call = p.session->newCall();
  cast::v1::SharedValue ref = reference(1, 0, 10);
  std::vector<std::shared_ptr<const cast::detail::LentBytes>> held;
  for (int i = 0; i < 64; ++i) {
    ref.set_value_id(static_cast<std::uint64_t>(i));
    held.push_back(call->claim(ref));
  }
  auto frames = framesFrom(p.server, p.reader);
  ASSERT_EQ(frames.size(), 1u);
  EXPECT_EQ(frames[0].body, le(1, 8) + le(64, 8) + std::string(1, '\0'));
  call.reset();  // ended without its answer read whole: says so
  frames = framesFrom(p.server, p.reader);
  ASSERT_FALSE(frames.empty());
  EXPECT_EQ(frames.back().body, le(1, 8) + le(64, 8) + "\x01");
}

TEST(SharedMemorySession, AReferenceThatDoesNotFitOrNamesNoSegmentIsRefusedAndGivenBack) {
  Pair p;
  p.offerSegment(1, std::string(4096, 's'), 4096);
  auto call = p.session->newCall();
  try {
    call->claim(reference(1, 4000, 200, 9));  // past the segment's end
    FAIL() << "a reference past its segment was read";
  } catch (const cast::UnavailableError& e) {
    EXPECT_NE(e.message().find("which has 4096"), std::string::npos) << e.message();
  }
  auto frames = framesFrom(p.server, p.reader);
  ASSERT_EQ(frames.size(), 1u);
  EXPECT_EQ(frames[0].kind, shm::kRelease);
  EXPECT_EQ(frames[0].body, le(9, 8));
  // A segment never sent, from a server that is gone: refused at once.
  ::shutdown(p.server, SHUT_RDWR);
  EXPECT_THROW(call->claim(reference(2, 0, 1, 9)), cast::UnavailableError);
  EXPECT_TRUE(p.session->dead());
  EXPECT_EQ(p.session->why(), "the server closed the session");
  EXPECT_FALSE(p.session->stage(std::string(2000, 'z')));  // a dead session stages nothing
}

TEST(SharedMemorySession, ALentValueIsMappedReadOnly) {
  Pair p;
  p.offerSegment(1, std::string(4096, 'r'), 4096);
  auto call = p.session->newCall();
  auto lent = call->claim(reference(1, 0, 4096));
  void* page = const_cast<char*>(lent->data());
  EXPECT_NE(::mprotect(page, 4096, PROT_READ | PROT_WRITE), 0);  // the seal refuses it
  EXPECT_EQ(errno, EACCES);
}

TEST(SharedMemorySession, RefusedEndsTheSessionAndUnknownFramesAreIgnored) {
  Pair p;
  const int stray = ::memfd_create("stray", MFD_CLOEXEC);
  sendWith(p.server, frame(42, "future"), stray);  // a kind this client does not know, with a descriptor
  ::close(stray);
  p.session->poll(std::chrono::milliseconds(200));
  EXPECT_FALSE(p.session->dead());
  sendWith(p.server, frame(shm::kRefused, "bad token"), -1);
  p.session->poll(std::chrono::milliseconds(200));
  EXPECT_TRUE(p.session->dead());
  EXPECT_EQ(p.session->why(), "the server ended it: bad token");
}

// A read that came back short found the socket empty: the session does not
// read again only to hear EAGAIN; a read that filled its buffer is followed
// by another. (Frames of a kind this client does not know are skipped.)
TEST(SharedMemorySession, ReadsTheSocketUntilAReadComesBackShort) {
  Pair p;
  sendWith(p.server, frame(42, "small"), -1);
  const std::uint64_t before = p.session->socketReads();
  p.session->poll(std::chrono::milliseconds(200));
  EXPECT_EQ(p.session->socketReads() - before, 1u);
  // More than one read's buffer (kMaxFrame): a full read, then a short one.
  sendWith(p.server, frame(42, std::string(shm::kMaxFrame - 5, 'x')) + frame(42, std::string(1000, 'y')), -1);
  const std::uint64_t full = p.session->socketReads();
  p.session->poll(std::chrono::milliseconds(200));
  EXPECT_EQ(p.session->socketReads() - full, 2u);
  EXPECT_FALSE(p.session->dead());
}

}  // namespace
