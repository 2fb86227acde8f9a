// A watch's events on the shared-memory session's socket (src/watch_stream.cc,
// src/shm_session.cc) against the repository's Python server: a C++
// component with a session asks for its Watch call's event batches as EVENTS
// frames (docs/client-protocol.md, "A watch's events on the session's
// socket"), which the session's reader thread queues for its callbacks.
// Large and small values reach the callbacks each once, in order, by frames;
// a watch whose socket ends resumes on a new call without gap or duplicate,
// by frames again; a callback that is slow lets the writer go on, and one
// that writes while its queue is full still gets its replies (they share the
// socket). The other tests of this binary run on the socket too: their
// components have sessions (delivery_test.cc's `latest`, the views of
// shared_memory_test.cc).
#include <google/protobuf/wrappers.pb.h>
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <future>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "cast/cast.h"
#include "cast/grpc_transport.h"
#include "cast_server.h"
#include "shm_session.h"

namespace {

using namespace std::chrono_literals;
using cast::detail::ClientSession;
using cast::testing::CastServer;
using cast::testing::endSessionSockets;
using cast::testing::eventually;
using cast::testing::kMiB;
using cast::testing::sharedServer;
using google::protobuf::BytesValue;
using google::protobuf::Int64Value;

// A value of `size` bytes whose first byte is its seed.
BytesValue seeded(std::size_t size, int seed) {
  BytesValue v;
  v.set_value(std::string(size, static_cast<char>(seed % 251)));
  return v;
}

// What a watcher's callbacks saw: each value's seed (its first byte), through its view.
struct Seeds {
  std::mutex mu;
  std::vector<int> seeds;
  std::size_t size() {
    std::lock_guard<std::mutex> lock(mu);
    return seeds.size();
  }
  std::vector<int> copy() {
    std::lock_guard<std::mutex> lock(mu);
    return seeds;
  }
  cast::ChangeCallback callback() {
    return [this](const cast::WorkingMemoryChange& change) {
      if (change.operation() == cast::Operation::Delete) return;
      cast::ValueView view = change.view();
      const int seed = static_cast<int>(static_cast<unsigned char>(view.field(1)[0]));
      std::lock_guard<std::mutex> lock(mu);
      seeds.push_back(seed);
    };
  }
};

std::vector<int> firstSeeds(int count) {
  std::vector<int> out;
  for (int i = 0; i < count; ++i) out.push_back(i % 251);
  return out;
}

// A write that may meet a session just ended: tried again until it is applied.
template <class Write>
void appliedOnce(Write&& write) {
  ASSERT_TRUE(eventually([&] {
    try {
      write();
      return true;
    } catch (const cast::UnavailableError&) {
      return false;
    }
  }));
}

TEST(SocketEvents, LargeValuesReachTheCallbacksAsFramesOnTheSessionsSocketEachOnceInOrder) {
  auto writer = sharedServer().connect("se-writer", "vision");
  auto watcher = sharedServer().connect("se-watcher", "vision");
  Seeds seen;
  watcher->onChange(cast::addressFilter("se-img").withEntry(), seen.callback());
  const std::uint64_t before = ClientSession::eventFramesHandled();
  writer->add("se-img", seeded(kMiB, 0));
  for (int i = 1; i < 20; ++i) writer->overwrite("se-img", seeded(kMiB, i));
  ASSERT_TRUE(eventually([&] { return seen.size() >= 20; }));
  std::this_thread::sleep_for(200ms);  // nothing more comes: each once
  EXPECT_EQ(seen.copy(), firstSeeds(20));
  // They came as frames (a batch each, or fewer batches of several).
  EXPECT_GE(ClientSession::eventFramesHandled() - before, 1u);
}

TEST(SocketEvents, TheDispatcherThreadReadsTheFramesItselfWithNoReaderThread) {
  // A watcher that does not write: its component's dispatcher thread waits on the session's
  // socket and runs each event's callback on the thread that read its frame.
  auto writer = sharedServer().connect("se-direct-writer", "vision");
  auto watcher = sharedServer().connect("se-direct-watcher", "vision");
  const std::uint64_t readers = ClientSession::readersStarted();
  const std::uint64_t before = ClientSession::eventFramesHandled();
  Seeds seen;
  watcher->onChange(cast::addressFilter("se-direct").withEntry(), seen.callback());
  writer->add("se-direct", seeded(kMiB, 0));
  for (int i = 1; i < 10; ++i) writer->overwrite("se-direct", seeded(kMiB, i));
  ASSERT_TRUE(eventually([&] { return seen.size() >= 10; }));
  EXPECT_EQ(seen.copy(), firstSeeds(10));
  EXPECT_GE(ClientSession::eventFramesHandled() - before, 1u);
  EXPECT_EQ(ClientSession::readersStarted(), readers);  // no thread between the socket and the callbacks
}

TEST(SocketEvents, SmallValuesComeInTheFramesAsBytes) {
  auto writer = sharedServer().connect("se-small-writer", "vision");
  auto watcher = sharedServer().connect("se-small-watcher", "vision");
  std::mutex mu;
  std::vector<std::int64_t> got;
  watcher->onChange(cast::addressFilter("se-small").withEntry(), [&](const cast::WorkingMemoryChange& change) {
    std::lock_guard<std::mutex> lock(mu);
    got.push_back(change.entry<Int64Value>().value.value());
    EXPECT_FALSE(change.view().shared());
  });
  const std::uint64_t before = ClientSession::eventFramesHandled();
  writer->add("se-small", cast::testing::number(1));
  writer->overwrite("se-small", cast::testing::number(2));
  writer->overwrite("se-small", cast::testing::number(3));
  ASSERT_TRUE(eventually([&] {
    std::lock_guard<std::mutex> lock(mu);
    return got.size() >= 3;
  }));
  std::lock_guard<std::mutex> lock(mu);
  EXPECT_EQ(got, (std::vector<std::int64_t>{1, 2, 3}));
  EXPECT_GE(ClientSession::eventFramesHandled() - before, 1u);
}

TEST(SocketEvents, AWatchWhoseSocketEndsResumesOnANewCallWithoutGapOrDuplicate) {
  CastServer server;  // its own: its sessions are ended here
  auto writer = server.connect("se-rs-writer", "vision");
  auto watcher = server.connect("se-rs-watcher", "vision");
  Seeds seen;
  watcher->onChange(cast::addressFilter("se-rs").withEntry(), seen.callback());
  writer->add("se-rs", seeded(kMiB, 0));
  for (int i = 1; i < 10; ++i) writer->overwrite("se-rs", seeded(kMiB, i));
  ASSERT_TRUE(eventually([&] { return seen.size() >= 10; }));
  ASSERT_GT(endSessionSockets(), 0);
  const std::uint64_t ended = ClientSession::eventFramesHandled();
  for (int i = 10; i < 40; ++i) appliedOnce([&] { writer->overwrite("se-rs", seeded(kMiB, i)); });
  ASSERT_TRUE(eventually([&] { return seen.size() >= 40; })) << seen.size();
  std::this_thread::sleep_for(200ms);  // nothing more comes: each once
  EXPECT_EQ(seen.copy(), firstSeeds(40));
  // The watch resumed on a new session, by frames again.
  EXPECT_TRUE(eventually([&] {
    appliedOnce([&] { writer->overwrite("se-rs", seeded(kMiB, 40)); });
    return ClientSession::eventFramesHandled() > ended;
  }));
}

// A component whose queue holds `capacity` callbacks.
class SmallQueue : public cast::UnmanagedComponent {
 public:
  explicit SmallQueue(std::size_t capacity) { setMaxPendingCallbacks(capacity); }
  ~SmallQueue() override { close(); }
};

std::unique_ptr<SmallQueue> smallQueue(const CastServer& server, const std::string& id, std::size_t capacity) {
  auto component = std::make_unique<SmallQueue>(capacity);
  component->bind(cast::connectGrpc(server.endpoint(), server.token(id, "vision"), {id, "vision", false}));
  return component;
}

TEST(SocketEvents, ASlowCallbackLetsTheWriterGoOnAndThenGetsEveryValueOnceInOrder) {
  auto writer = sharedServer().connect("se-slow-writer", "vision");
  auto watcher = smallQueue(sharedServer(), "se-slow-watcher", 4);
  std::promise<void> gate;
  std::shared_future<void> open = gate.get_future().share();
  Seeds seen;
  auto take = seen.callback();
  watcher->onChange(cast::addressFilter("se-slow").withEntry(), [&](const cast::WorkingMemoryChange& change) {
    open.wait();  // the first callback holds the dispatcher until the writer is done
    take(change);
  });
  writer->add("se-slow", seeded(kMiB, 0));
  const auto started = std::chrono::steady_clock::now();
  for (int i = 1; i < 30; ++i) writer->overwrite("se-slow", seeded(kMiB, i));
  // Well inside the writes' deadlines: the server did not wait for the watcher.
  EXPECT_LT(std::chrono::steady_clock::now() - started, 10s);
  gate.set_value();
  ASSERT_TRUE(eventually([&] { return seen.size() >= 30; })) << seen.size();
  std::this_thread::sleep_for(200ms);
  EXPECT_EQ(seen.copy(), firstSeeds(30));
}

TEST(SocketEvents, ACallbackThatWritesWhileItsQueueIsFullGetsItsReplies) {
  // The replies of its writes come on the socket that carries its events: the
  // reader reads it for them while the queue is full.
  auto writer = sharedServer().connect("se-echo-writer", "vision");
  auto echo = smallQueue(sharedServer(), "se-echo", 2);
  std::atomic<int> echoed{0};
  std::atomic<int> failed{0};
  Seeds seen;
  auto take = seen.callback();
  echo->onChange(cast::addressFilter("se-echo-in").withEntry(), [&](const cast::WorkingMemoryChange& change) {
    take(change);
    std::this_thread::sleep_for(5ms);  // the queue fills meanwhile
    try {
      echo->overwrite("se-echo-out", cast::testing::number(echoed.load() + 1));
      ++echoed;
    } catch (const cast::CastError&) {
      ++failed;
    }
  });
  echo->add("se-echo-out", cast::testing::number(0));
  writer->add("se-echo-in", seeded(kMiB, 0));
  std::vector<std::future<cast::WriteResult>> burst;
  for (int i = 1; i < 30; ++i) burst.push_back(writer->overwriteAsync("se-echo-in", seeded(kMiB, i)));
  for (auto& f : burst) f.get();
  ASSERT_TRUE(eventually([&] { return echoed.load() + failed.load() >= 30; }, 30s)) << echoed.load();
  EXPECT_EQ(failed.load(), 0);
  EXPECT_EQ(seen.copy(), firstSeeds(30));
  EXPECT_EQ(writer->get<Int64Value>("se-echo-out").value(), 30);
}

}  // namespace
