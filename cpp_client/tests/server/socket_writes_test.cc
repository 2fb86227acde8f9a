// Writes on the shared-memory session's socket (src/socket_writes.cc) against
// the repository's Python server: a C++ component on the server's host sends
// every write there (docs/client-protocol.md, "Writes on the session's
// socket"). A mix of staged and small values, waited for and pipelined, is
// applied once each in call order; pipelined writes outstanding when the
// component closes are answered first; a socket that ends under outstanding
// writes fails them with UnavailableError naming the session, and the next
// writes succeed. (The Write stream's own tests, write_stream_test.cc, run on
// the socket too, since their components have sessions.)
#include <google/protobuf/wrappers.pb.h>
#include <gtest/gtest.h>

#include <future>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "cast/cast.h"
#include "cast_server.h"
#include "shm_session.h"

namespace {

using namespace std::chrono_literals;
using cast::testing::CastServer;
using cast::testing::contains;
using cast::testing::endSessionSockets;
using cast::testing::eventually;
using cast::testing::kMiB;
using cast::testing::sharedServer;
using google::protobuf::BytesValue;

BytesValue value(std::size_t size, int seed) {
  BytesValue v;
  v.set_value(std::string(size, static_cast<char>('a' + seed % 26)));
  return v;
}

TEST(SocketWrites, AMixOfStagedAndSmallValuesWaitedForAndPipelinedIsAppliedOnceInCallOrder) {
  auto writer = sharedServer().connect("sw-writer", "vision");
  auto watcher = sharedServer().connect("sw-watcher", "vision");
  std::mutex mu;
  std::vector<std::pair<std::uint64_t, std::string>> seen;  // (version, value)
  watcher->onChange(cast::addressFilter("sw-x").withEntry(), [&](const cast::WorkingMemoryChange& change) {
    if (change.operation() == cast::Operation::Delete) return;
    std::lock_guard<std::mutex> lock(mu);
    seen.emplace_back(change.version(), change.entry<BytesValue>().value.value());
  });
  std::vector<BytesValue> values;
  for (int i = 0; i < 24; ++i) values.push_back(value(i % 3 == 0 ? kMiB : 16 + i, i));  // staged and small
  std::vector<std::uint64_t> versions;
  versions.push_back(writer->add("sw-x", values[0]).version);
  std::vector<std::future<cast::WriteResult>> pipelined;
  for (std::size_t i = 1; i < values.size(); ++i) {
    if (i % 4 == 0) {
      for (auto& f : pipelined) versions.push_back(f.get().version);
      pipelined.clear();
      versions.push_back(writer->overwrite("sw-x", values[i]).version);
    } else {
      pipelined.push_back(writer->overwriteAsync("sw-x", values[i]));
    }
  }
  for (auto& f : pipelined) versions.push_back(f.get().version);
  ASSERT_TRUE(eventually([&] {
    std::lock_guard<std::mutex> lock(mu);
    return seen.size() >= values.size();
  }));
  std::this_thread::sleep_for(200ms);  // nothing more comes: each was applied once
  std::lock_guard<std::mutex> lock(mu);
  ASSERT_EQ(seen.size(), values.size());
  for (std::size_t i = 0; i < values.size(); ++i) {
    EXPECT_EQ(seen[i].first, versions[i]) << "write " << i;
    EXPECT_TRUE(seen[i].second == values[i].value()) << "write " << i;
  }
  EXPECT_TRUE(writer->get<BytesValue>("sw-x").value() == values.back().value());
}

TEST(SocketWrites, ASequentialWriterReadsItsOwnRepliesAndAPipelinedOneStartsTheReaderThread) {
  using cast::detail::ClientSession;
  auto writer = sharedServer().connect("sw-sequential", "vision");
  auto reader = sharedServer().connect("sw-sequential-reader", "vision");
  const std::uint64_t before = ClientSession::readersStarted();
  for (int i = 0; i < 20; ++i) writer->add("sw-s" + std::to_string(i), value(i % 4 == 0 ? kMiB : 8, i));
  { cast::LockGuard held = writer->lock("sw-s0"); }  // a lock and its unlock, waited for too
  // Each reply read by the thread that waited for it: no reader thread, no hand-off from one.
  EXPECT_EQ(ClientSession::readersStarted(), before);
  EXPECT_TRUE(reader->exists("sw-s19"));
  std::future<cast::WriteResult> pipelined = writer->addAsync("sw-s-async", value(8, 1));
  EXPECT_NO_THROW(pipelined.get());  // read by the reader thread it started: nobody waits on its reply
  EXPECT_EQ(ClientSession::readersStarted(), before + 1);
}

TEST(SocketWrites, PipelinedWritesOutstandingWhenTheComponentClosesAreAnsweredFirst) {
  auto writer = sharedServer().connect("sw-closer", "vision");
  std::vector<std::future<cast::WriteResult>> adds;
  for (int i = 0; i < 100; ++i) adds.push_back(writer->addAsync("sw-c" + std::to_string(i), value(i % 2 ? kMiB : 8, i)));
  writer.reset();  // closes: the session ends after its outstanding writes were answered
  for (auto& f : adds) EXPECT_NO_THROW(f.get());
  auto reader = sharedServer().connect("sw-close-reader", "vision");
  EXPECT_TRUE(reader->exists("sw-c99"));
}

TEST(SocketWrites, ASocketThatEndsFailsTheOutstandingWritesAsUnavailableAndLaterWritesSucceed) {
  CastServer server;  // its own: its sessions are ended here
  auto holder = server.connect("sw-holder", "vision");
  auto waiter = server.connect("sw-waiter", "vision");
  holder->add("sw-l", value(8, 1));
  cast::LockGuard held = holder->lock("sw-l");
  std::thread waiting;
  std::future<std::string> failed = cast::testing::lockOnAThread(*waiter, "sw-l", waiting);
  std::this_thread::sleep_for(300ms);  // the lock request reaches the server and waits there
  ASSERT_GT(endSessionSockets(), 0);
  ASSERT_EQ(failed.wait_for(20s), std::future_status::ready);
  waiting.join();
  const std::string message = failed.get();
  EXPECT_TRUE(contains(message, "the shared-memory session with " + server.endpoint() + " ended")) << message;
  EXPECT_TRUE(contains(message, "may or may not have been applied")) << message;
  // Later writes succeed (on a new session, or the gRPC stream meanwhile), in order, large ones too.
  const BytesValue big = value(kMiB, 2);
  EXPECT_TRUE(eventually([&] {
    try {
      waiter->add("sw-after", value(8, 3));
      return true;
    } catch (const cast::UnavailableError&) {
      return false;
    }
  }));
  waiter->overwrite("sw-after", big);
  EXPECT_TRUE(holder->get<BytesValue>("sw-after").value() == big.value());
  held.release();
}

TEST(SocketWrites, ALargeWriteAfterTheTokenWasRenewedIsStagedInTheNewSessionItGoesOn) {
  CastServer& server = sharedServer();
  const std::string path = server.dir() + "/sw-renewed.token";
  cast::testing::writeTokenFile(path, server.token("sw-renewed", "vision"));
  cast::TransportOptions options;
  options.tokenFile = path;
  auto writer = server.connect("sw-renewed", "vision", options);
  auto reader = server.connect("sw-renewed-reader", "vision");
  writer->add("sw-r", value(kMiB, 1));
  std::this_thread::sleep_for(1100ms);  // a token issued later differs; the file is looked at once a second
  cast::testing::writeTokenFile(path, server.token("sw-renewed", "vision"));
  // Staged in a session opened with the new token, the one the write then goes on: staged in the old
  // one, which the write's renewal ends, the server would refuse it (its session is gone).
  const BytesValue big = value(kMiB, 2);
  writer->overwrite("sw-r", big);
  EXPECT_TRUE(reader->get<BytesValue>("sw-r").value() == big.value());
}

}  // namespace
