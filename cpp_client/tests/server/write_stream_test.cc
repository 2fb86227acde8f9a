// Writes and locks on the WorkingMemory.Write stream (src/write_stream.cc)
// against the repository's Python server: the same results and named errors
// as the unary calls gave, pipelined writes in call order with their errors
// on the futures, many threads at once, a value of 1.5 MiB end to end, a
// renewed token, and a stream that breaks (which also shows that every kind
// of write travels on the stream). On the server's host these travel on the
// shared-memory session's socket (socket_writes.h); ctest runs them once more
// with CAST_SHARED_MEMORY=off, on the gRPC stream (server.WriteStreamByGrpc).
#include <google/protobuf/wrappers.pb.h>
#include <gtest/gtest.h>
#include <unistd.h>

#include <functional>
#include <future>
#include <string>
#include <thread>
#include <vector>

#include "cast/cast.h"
#include "cast_server.h"
#include "shm.h"

namespace {

using namespace std::chrono_literals;
using cast::BatchWrite;
using cast::LockMode;
using cast::testing::CastServer;
using cast::testing::contains;
using cast::testing::eventually;
using cast::testing::number;
using cast::testing::sharedServer;
using google::protobuf::BytesValue;
using google::protobuf::Int64Value;

TEST(WriteStream, WritesAndLocksAnswerAsTheUnaryCallsDid) {
  auto a = sharedServer().connect("ws-writer", "vision");
  auto b = sharedServer().connect("ws-other", "vision");
  const cast::WriteResult added = a->add("ws-x", number(1));
  const cast::WriteResult overwritten = a->overwrite("ws-x", number(2), "", added.version);
  EXPECT_GT(overwritten.revision, added.revision);
  EXPECT_GT(overwritten.version, added.version);
  EXPECT_THROW(a->add("ws-x", number(3)), cast::AlreadyExistsError);
  EXPECT_THROW(a->overwrite("ws-x", number(3), "", added.version), cast::ConsistencyError);
  EXPECT_THROW(a->overwrite("ws-missing", number(3)), cast::NotFoundError);
  try {
    a->add("ws-y", number(1), "language");
    FAIL() << "a write outside the own SA was accepted";
  } catch (const cast::PermissionDeniedError& e) {
    EXPECT_TRUE(contains(e.message(), "'ws-writer'")) << e.message();
  }

  // A batch: all or nothing, in order.
  EXPECT_EQ(a->batch({BatchWrite::add("ws-b1", number(1)), BatchWrite::overwrite("ws-b1", number(2)),
                      BatchWrite::deleteEntry("ws-b1")})
                .size(),
            3u);
  EXPECT_THROW(a->batch({BatchWrite::add("ws-b2", number(1)), BatchWrite::add("ws-x", number(1))}),
               cast::AlreadyExistsError);
  EXPECT_FALSE(a->exists("ws-b2"));

  // Locks: another holder is named, a timed wait ends, a waiting lock is
  // granted when the holder lets go.
  cast::LockGuard held = b->lock("ws-x", LockMode::OD);
  EXPECT_EQ(held.depth(), 1u);
  EXPECT_EQ(b->lock("ws-x", LockMode::OD).depth(), 2u);  // re-entrant; that guard unlocks at once
  try {
    a->overwrite("ws-x", number(9));
    FAIL() << "a write against another component's lock was accepted";
  } catch (const cast::LockedError& e) {
    EXPECT_TRUE(contains(e.message(), "ws-other")) << e.message();
  }
  EXPECT_FALSE(a->tryLock("ws-x"));
  EXPECT_THROW(a->lock("ws-x", LockMode::OD, "", 300ms), cast::DeadlineExceededError);
  std::thread letGo([&held] {
    std::this_thread::sleep_for(200ms);
    held.unlock();
  });
  cast::LockGuard mine = a->lock("ws-x", LockMode::OD, "", 20s);
  letGo.join();
  EXPECT_TRUE(mine.held());
  EXPECT_EQ(a->unlock("ws-x"), 0u);
  mine.release();
  EXPECT_THROW(a->unlock("ws-x"), cast::LockedError);  // no longer held

  const cast::WriteResult deleted = a->deleteEntry("ws-x", "", overwritten.version);
  EXPECT_EQ(deleted.version, overwritten.version);
  EXPECT_FALSE(b->exists("ws-x"));
}

TEST(WriteStream, PipelinedWritesAreAppliedInCallOrderWithTheirErrorsOnTheFutures) {
  auto a = sharedServer().connect("ws-pipeliner", "vision");
  std::vector<std::future<cast::WriteResult>> adds;
  for (int i = 0; i < 200; ++i) adds.push_back(a->addAsync("ws-p" + std::to_string(i), number(i)));
  std::future<cast::WriteResult> duplicate = a->addAsync("ws-p0", number(0));
  std::uint64_t last = 0;
  for (auto& f : adds) {
    const cast::WriteResult r = f.get();
    EXPECT_GT(r.revision, last);
    last = r.revision;
  }
  EXPECT_THROW(duplicate.get(), cast::AlreadyExistsError);

  const cast::WriteResult first = a->add("ws-count", number(0));
  std::vector<std::future<cast::WriteResult>> overwrites;
  for (int i = 1; i <= 50; ++i) overwrites.push_back(a->overwriteAsync("ws-count", number(i)));
  std::future<cast::WriteResult> stale = a->overwriteAsync("ws-count", number(-1), "", first.version);
  std::uint64_t version = first.version;
  for (auto& f : overwrites) {
    const cast::WriteResult r = f.get();
    EXPECT_GT(r.version, version);
    version = r.version;
  }
  EXPECT_THROW(stale.get(), cast::ConsistencyError);
  // A write that waits for its reply comes after the pipelined ones.
  EXPECT_EQ(a->overwrite("ws-count", number(51), "", version).version, version + 1);
  EXPECT_EQ(a->get<Int64Value>("ws-count").value(), 51);
  for (int i : {0, 99, 199}) EXPECT_EQ(a->get<Int64Value>("ws-p" + std::to_string(i)).value(), i);
}

TEST(WriteStream, ManyThreadsWriteAtOnce) {
  auto a = sharedServer().connect("ws-threads", "vision");
  std::vector<std::thread> threads;
  std::vector<std::string> failures(4);
  for (int t = 0; t < 4; ++t) {
    threads.emplace_back([&a, &failures, t] {
      try {
        const std::string id = "ws-thread" + std::to_string(t);
        cast::WriteResult r = a->add(id, number(0));
        std::vector<std::future<cast::WriteResult>> pipelined;
        for (int i = 1; i <= 50; ++i) {
          // Each thread's versioned overwrites check that its own writes keep their order.
          r = a->overwrite(id, number(i), "", r.version);
          pipelined.push_back(a->addAsync(id + "-" + std::to_string(i), number(i)));
        }
        for (auto& f : pipelined) f.get();
      } catch (const std::exception& e) {
        failures[static_cast<std::size_t>(t)] = e.what();
      }
    });
  }
  for (auto& t : threads) t.join();
  for (int t = 0; t < 4; ++t) {
    EXPECT_EQ(failures[static_cast<std::size_t>(t)], "");
    EXPECT_EQ(a->get<Int64Value>("ws-thread" + std::to_string(t)).value(), 50);
    EXPECT_TRUE(a->exists("ws-thread" + std::to_string(t) + "-50"));
  }
}

TEST(WriteStream, AValueOfOneAndAHalfMebibytesIsWrittenReadAndWatched) {
  auto writer = sharedServer().connect("ws-big-writer", "vision");
  auto watcher = sharedServer().connect("ws-big-watcher", "vision");
  std::string bytes(1536 * 1024, '\0');
  for (std::size_t i = 0; i < bytes.size(); ++i) bytes[i] = static_cast<char>((i * 131) % 251);
  std::mutex mu;
  std::vector<std::string> seen;
  watcher->onChange(cast::addressFilter("ws-big").withEntry(), [&](const cast::WorkingMemoryChange& change) {
    std::string value = change.entry<BytesValue>().value.value();
    std::lock_guard<std::mutex> lock(mu);
    seen.push_back(std::move(value));
  });
  BytesValue big;
  big.set_value(bytes);
  writer->add("ws-big", big);
  EXPECT_TRUE(watcher->get<BytesValue>("ws-big").value() == bytes);
  bytes[12345] = static_cast<char>(bytes[12345] ^ 0x5a);
  big.set_value(bytes);
  writer->overwriteAsync("ws-big", big).get();
  ASSERT_TRUE(eventually([&] {
    std::lock_guard<std::mutex> lock(mu);
    return seen.size() == 2;
  }));
  std::lock_guard<std::mutex> lock(mu);
  EXPECT_EQ(seen[0].size(), bytes.size());
  EXPECT_TRUE(seen[1] == bytes);
}

// 64 values of 1 MiB in flight at once (queued ones share messages, which
// must stay under gRPC's limit), and a request over that limit refused before
// it is sent: sent, it would end the stream and fail the others with it.
TEST(WriteStream, ManyLargeValuesInFlightAndOneOverTheMessageLimit) {
  auto writer = sharedServer().connect("ws-huge", "vision");
  std::string bytes(1024 * 1024, 'x');
  BytesValue value;
  value.set_value(bytes);
  cast::WriteResult last = writer->add("ws-huge", value);
  std::vector<std::future<cast::WriteResult>> inFlight;  // 64 MiB together
  for (int i = 0; i < 64; ++i) {
    bytes[0] = static_cast<char>(i);
    value.set_value(bytes);
    inFlight.push_back(writer->overwriteAsync("ws-huge", value));
  }
  BytesValue huge;
  huge.set_value(std::string(65 * 1024 * 1024, 'y'));
  try {
    writer->add("ws-too-big", huge);
    FAIL() << "a 65 MiB write was sent";
  } catch (const cast::InvalidArgumentError& e) {
    EXPECT_TRUE(contains(e.message(), "-byte limit of one request")) << e.message();
    EXPECT_TRUE(contains(e.message(), "limits.max_value_bytes")) << e.message();
  }
  for (auto& f : inFlight) {
    const cast::WriteResult r = f.get();
    EXPECT_GT(r.version, last.version);
    last = r;
  }
  EXPECT_EQ(writer->get<BytesValue>("ws-huge").value()[0], static_cast<char>(63));
  EXPECT_FALSE(writer->exists("ws-too-big"));
}

TEST(WriteStream, ARefusedTokenIsReadAgainFromItsFileAndTheWriteSentOnceMore) {
  CastServer& server = sharedServer();
  const std::string path = server.dir() + "/ws-renewed.token";
  cast::testing::writeTokenFile(path, server.token("ws-renewed", "vision"));
  cast::TransportOptions options;
  options.tokenFile = path;
  auto renewed = server.connect("ws-renewed", "vision", options);
  auto reader = server.connect("ws-token-reader", "vision");
  renewed->add("ws-t1", number(1));

  // A token the server refuses (another secret) replaces the file's: the
  // stream opened with it is refused, and the file has nothing newer.
  cast::testing::writeTokenFile(path,
                                server.token("ws-renewed", "vision", false, "another-secret-0123456789abcdef-012345"));
  std::this_thread::sleep_for(1100ms);  // the token file is looked at once a second at most
  EXPECT_THROW(renewed->add("ws-t2", number(2)), cast::UnauthenticatedError);
  EXPECT_FALSE(reader->exists("ws-t2"));

  // Renewed again: the refusal makes the client read the file at once, and
  // send the write once more, on a stream opened with the new token.
  cast::testing::writeTokenFile(path, server.token("ws-renewed", "vision"));
  renewed->add("ws-t2", number(2));
  EXPECT_EQ(reader->get<Int64Value>("ws-t2").value(), 2);
}

TEST(WriteStream, ABrokenStreamFailsWhatIsOutstandingAndTheNextWriteReconnects) {
  CastServer server;  // its own: this test kills it
  auto holder = server.connect("ws-holder", "vision");
  auto waiter = server.connect("ws-waiter", "vision");
  holder->add("ws-l", number(1));
  waiter->add("ws-w", number(1));  // registers the type's schema (a unary call) while the server is there
  cast::LockGuard held = holder->lock("ws-l");
  std::thread waiting;
  std::future<std::string> failed = cast::testing::lockOnAThread(*waiter, "ws-l", waiting);
  std::this_thread::sleep_for(300ms);  // the lock request reaches the server and waits there
  server.kill();
  ASSERT_EQ(failed.wait_for(20s), std::future_status::ready);
  waiting.join();
  const std::string message = failed.get();
  // On the server's host the lock went on the shared-memory session's socket, which ended with the
  // server; with shared memory off (ctest's server.WriteStreamByGrpc), on the gRPC stream.
  const std::string broke = cast::detail::sharedMemoryTurnedOff()
                                ? "the write stream to " + server.endpoint() + " broke"
                                : "the shared-memory session with " + server.endpoint() + " ended";
  EXPECT_TRUE(contains(message, broke)) << message;
  EXPECT_TRUE(contains(message, "may or may not have been applied")) << message;
  // Every kind of write goes on the stream: with the server away, each fails
  // as the stream it tried does.
  const std::vector<std::pair<const char*, std::function<void()>>> writes = {
      {"add", [&] { waiter->add("ws-away", number(1)); }},
      {"overwrite", [&] { waiter->overwrite("ws-l", number(2)); }},
      {"deleteEntry", [&] { waiter->deleteEntry("ws-l"); }},
      {"batch", [&] { waiter->batch({BatchWrite::add("ws-away", number(1))}); }},
      {"tryLock", [&] { waiter->tryLock("ws-l"); }},
      {"unlock", [&] { waiter->unlock("ws-l"); }},
      {"addAsync", [&] { waiter->addAsync("ws-away", number(1)).get(); }},
      {"overwriteAsync", [&] { waiter->overwriteAsync("ws-l", number(2)).get(); }},
  };
  for (const auto& [name, write] : writes) {
    try {
      write();
      ADD_FAILURE() << name << " succeeded with the server away";
    } catch (const cast::UnavailableError& e) {
      EXPECT_TRUE(contains(e.message(), "the write stream to " + server.endpoint())) << name << ": " << e.message();
    }
  }

  server.restart();
  EXPECT_TRUE(eventually([&] {
    try {
      waiter->add("ws-after", number(1));
      return true;
    } catch (const cast::UnavailableError&) {
      return false;
    } catch (const cast::AlreadyExistsError&) {
      return true;  // an earlier try was applied after all
    }
  })) << server.log();
  EXPECT_EQ(holder->get<Int64Value>("ws-after").value(), 1);
  held.release();  // that lock ended with the first server
}

}  // namespace
