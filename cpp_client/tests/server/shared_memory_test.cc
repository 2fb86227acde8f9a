// Large values by shared memory between C++ clients and the repository's
// Python server on this host (docs/client-protocol.md, "Large values by
// shared memory"): values go by reference both ways and read back
// identical, through get<T>, getEntry, getAll, callbacks and views; the
// staging area's regions are reused; a write cannot change a value after it
// was acknowledged, a reader cannot write what it was lent; forged and stale
// references are refused and change nothing; CAST_SHARED_MEMORY=off gives the
// same values as bytes, said once at INFO; a dead server's memory is unmapped.
// The server's figures (GetMetrics' shared_memory) show which path a value took.
#include <fcntl.h>
#include <google/protobuf/wrappers.pb.h>
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>
#include <sys/mman.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <functional>
#include <future>
#include <mutex>
#include <string>
#include <vector>

#include "cast/cast.h"
#include "cast/v1/directory.grpc.pb.h"
#include "cast/v1/working_memory.grpc.pb.h"
#include "cast_server.h"
#include "shm.h"

namespace {

using namespace std::chrono_literals;
using cast::testing::CastServer;
using cast::testing::contains;
using cast::testing::eventually;
using cast::testing::image;
using cast::testing::kMiB;
using cast::testing::sharedServer;
using google::protobuf::BytesValue;

// What the test process has mapped of any server's shared memory.
int memoryFilesMapped() {
  std::ifstream maps("/proc/self/maps");
  std::string line;
  int n = 0;
  while (std::getline(maps, line)) n += contains(line, "memfd:cast-") ? 1 : 0;
  return n;
}

// Raw calls to a server, as any gRPC client makes them.
class Raw {
 public:
  explicit Raw(const CastServer& server)
      : server_(server), channel_(grpc::CreateChannel(server.endpoint(), grpc::InsecureChannelCredentials())),
        wm_(cast::v1::WorkingMemory::NewStub(channel_)) {}

  cast::v1::SharedMemoryMetrics metrics() { return cast::testing::sharedMemoryFigures(server_); }

  // A session of `component` opened as any client opens one.
  std::shared_ptr<cast::detail::ClientSession> session(const std::string& component) {
    grpc::ClientContext ctx;
    auth(ctx, component);
    cast::v1::SystemDescription desc;
    EXPECT_TRUE(cast::v1::Directory::NewStub(channel_)->DescribeSystem(&ctx, {}, &desc).ok());
    EXPECT_TRUE(desc.has_shared_memory());
    return cast::detail::connectShared(desc.shared_memory(), server_.token(component, "vision"), server_.endpoint());
  }

  grpc::Status overwrite(const std::string& component, const cast::v1::OverwriteRequest& request) {
    grpc::ClientContext ctx;
    auth(ctx, component);
    cast::v1::WriteResponse resp;
    return wm_->Overwrite(&ctx, request, &resp);
  }

  grpc::Status get(const std::string& component, const std::string& id, const std::string& sharedMetadata,
                   cast::v1::Entry* entry = nullptr) {
    grpc::ClientContext ctx;
    auth(ctx, component);
    if (!sharedMetadata.empty()) ctx.AddMetadata(cast::detail::kSharedMemoryMetadata, sharedMetadata);
    cast::v1::GetRequest req;
    req.mutable_address()->set_id(id);
    req.mutable_address()->set_subarchitecture("vision");
    cast::v1::GetResponse resp;
    const grpc::Status status = wm_->Get(&ctx, req, &resp);
    if (entry != nullptr) *entry = resp.entry();
    return status;
  }

 private:
  void auth(grpc::ClientContext& ctx, const std::string& component) {
    ctx.AddMetadata("authorization", "Bearer " + server_.token(component, "vision"));
  }
  const CastServer& server_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<cast::v1::WorkingMemory::Stub> wm_;
};

// An overwrite of `id` whose value `session` staged.
cast::v1::OverwriteRequest stagedOverwrite(cast::detail::ClientSession& session, const std::string& id,
                                           const BytesValue& value, cast::detail::Staged* where = nullptr) {
  const std::string data = value.SerializeAsString();
  std::optional<cast::detail::Staged> staged = session.stage(data);
  EXPECT_TRUE(staged);
  if (where != nullptr) *where = *staged;
  cast::v1::OverwriteRequest request;
  request.mutable_address()->set_id(id);
  request.mutable_address()->set_subarchitecture("vision");
  request.mutable_value()->set_type_url("type.googleapis.com/google.protobuf.BytesValue");
  session.describe(*staged, request.mutable_staged_value());
  return request;
}

TEST(SharedMemory, LargeValuesGoByReferenceAndReadBackIdenticalThroughEveryRead) {
  Raw raw(sharedServer());
  auto writer = sharedServer().connect("shm-writer", "vision");
  auto reader = sharedServer().connect("shm-reader", "vision");
  const auto before = raw.metrics();
  std::mutex mu;
  struct Seen {
    std::uint64_t revision;
    std::string value;
    bool shared;
    bool same;  // the view read what the decoded entry holds
  };
  std::vector<Seen> seen;
  reader->onChange(cast::addressFilter("shm-img").withEntry(), [&](const cast::WorkingMemoryChange& change) {
    cast::ValueView view = change.view();
    const std::string decoded = change.entry<BytesValue>().value.value();
    std::lock_guard<std::mutex> lock(mu);
    seen.push_back({change.revision(), decoded, view.shared(), view.field(1).chars() == decoded});
  });
  const std::vector<BytesValue> frames = {image(kMiB, 0), image(kMiB, 1), image(kMiB, 2)};
  std::vector<std::uint64_t> revisions;
  revisions.push_back(writer->add("shm-img", frames[0]).revision);
  revisions.push_back(writer->overwrite("shm-img", frames[1]).revision);
  revisions.push_back(writer->overwrite("shm-img", frames[2]).revision);
  BytesValue tiny;
  tiny.set_value("tiny");
  writer->add("shm-small", tiny);
  ASSERT_TRUE(eventually([&] {
    std::lock_guard<std::mutex> lock(mu);
    return seen.size() == 3;
  }));
  for (std::size_t i = 0; i < 3; ++i) {
    EXPECT_EQ(seen[i].revision, revisions[i]);
    EXPECT_TRUE(seen[i].value == frames[i].value()) << "frame " << i;
    EXPECT_TRUE(seen[i].shared) << "frame " << i << " came as bytes";
    EXPECT_TRUE(seen[i].same) << "frame " << i;
  }
  EXPECT_TRUE(reader->get<BytesValue>("shm-img").value() == frames[2].value());
  const auto entry = reader->getEntry<BytesValue>("shm-img");
  EXPECT_TRUE(entry.value.value() == frames[2].value());
  bool found = false;
  for (const auto& e : reader->getAll<BytesValue>()) {
    if (e.id() == "shm-img") found = e.value.value() == frames[2].value();
  }
  EXPECT_TRUE(found);
  {
    cast::ValueView view = reader->getView("shm-img");
    EXPECT_TRUE(view.shared());
    EXPECT_EQ(view.type(), "google.protobuf.BytesValue");
    EXPECT_EQ(view.version(), entry.version);
    EXPECT_EQ(view.author(), "shm-writer");
    EXPECT_TRUE(view.field(1).chars() == frames[2].value());
    // The pixels start on a cache line (the server's arena aligns a value's largest bytes field), so an
    // array over them (Eigen, OpenCV, SIMD loads) is aligned.
    EXPECT_EQ(reinterpret_cast<std::uintptr_t>(view.field(1).data()) % 64, 0u);
    EXPECT_TRUE(view.decode<BytesValue>().value() == frames[2].value());
    cast::ValueView small = reader->getView("shm-small");
    EXPECT_FALSE(small.shared());
    EXPECT_EQ(small.field(1).chars(), "tiny");
  }
  const auto after = raw.metrics();
  EXPECT_EQ(after.staged_writes() - before.staged_writes(), 3u);  // the C++ writer staged its three
  EXPECT_GE(after.lent() - before.lent(), 3u + 4u);              // three events, four large reads
  {
    std::lock_guard<std::mutex> lock(mu);
    seen.clear();
  }
  reader->drain();
  // Every value lent is given back once nothing holds it.
  EXPECT_TRUE(eventually([&] { return raw.metrics().lent_bytes() == 0; })) << raw.metrics().lent_bytes();
}

TEST(SharedMemory, TheStagingAreaIsReusedAfterAsyncAndBatchedWrites) {
  Raw raw(sharedServer());
  auto writer = sharedServer().connect("shm-async", "vision");
  const auto before = raw.metrics();
  writer->add("shm-a", image(kMiB, 0));
  // More in flight than the staging area (two of the largest values) holds: the rest go as bytes.
  std::vector<std::future<cast::WriteResult>> futures;
  for (int i = 1; i <= 30; ++i) futures.push_back(writer->overwriteAsync("shm-a", image(kMiB, i % 251)));
  std::uint64_t last = 0;
  for (auto& f : futures) {
    const cast::WriteResult r = f.get();
    EXPECT_GT(r.version, last);
    last = r.version;
  }
  EXPECT_TRUE(writer->get<BytesValue>("shm-a").value() == image(kMiB, 30).value());
  const auto middle = raw.metrics();
  EXPECT_GE(middle.staged_writes() - before.staged_writes(), 2u);
  // Every region was given back: 20 more writes, one at a time, are all staged.
  for (int i = 0; i < 20; ++i) writer->overwrite("shm-a", image(kMiB, i));
  writer->batch({cast::BatchWrite::overwrite("shm-a", image(kMiB, 5)), cast::BatchWrite::add("shm-b", image(kMiB, 6))});
  const auto after = raw.metrics();
  EXPECT_EQ(after.staged_writes() - middle.staged_writes(), 22u);
  EXPECT_TRUE(writer->get<BytesValue>("shm-b").value() == image(kMiB, 6).value());
}

TEST(SharedMemory, AWriterCannotChangeAValueAfterItsWriteWasAcknowledged) {
  Raw raw(sharedServer());
  auto reader = sharedServer().connect("shm-witness", "vision");
  auto writer = sharedServer().connect("shm-changer", "vision");
  writer->add("shm-fixed", image(kMiB, 1));
  auto session = raw.session("shm-changer");
  cast::detail::Staged first;
  ASSERT_TRUE(raw.overwrite("shm-changer", stagedOverwrite(*session, "shm-fixed", image(kMiB, 2), &first)).ok());
  // The writer writes its staging area again, where that value was.
  session->unstage(first, true);
  std::optional<cast::detail::Staged> again = session->stage(image(kMiB, 3).SerializeAsString());
  ASSERT_TRUE(again);
  EXPECT_EQ(again->offset, first.offset);
  EXPECT_TRUE(reader->get<BytesValue>("shm-fixed").value() == image(kMiB, 2).value());
  EXPECT_TRUE(reader->getView("shm-fixed").field(1).chars() == image(kMiB, 2).value());
}

TEST(SharedMemory, AReaderCannotWriteWhatItWasLent) {
  auto writer = sharedServer().connect("shm-w2", "vision");
  auto reader = sharedServer().connect("shm-r2", "vision");
  writer->add("shm-ro", image(kMiB, 4));
  cast::ValueView view = reader->getView("shm-ro");
  ASSERT_TRUE(view.shared());
  const long page = ::sysconf(_SC_PAGESIZE);
  auto* at = const_cast<std::byte*>(view.data().data());
  void* first = reinterpret_cast<void*>(reinterpret_cast<std::uintptr_t>(at) & ~static_cast<std::uintptr_t>(page - 1));
  EXPECT_NE(::mprotect(first, static_cast<std::size_t>(page), PROT_READ | PROT_WRITE), 0);
  // The memory file behind the mapping, opened again read-write: the seal refuses writes.
  std::ifstream maps("/proc/self/maps");
  std::string line, range;
  const auto address = reinterpret_cast<std::uintptr_t>(at);
  while (std::getline(maps, line)) {
    const std::string r = line.substr(0, line.find(' '));
    const auto dash = r.find('-');
    if (std::stoull(r.substr(0, dash), nullptr, 16) <= address && address < std::stoull(r.substr(dash + 1), nullptr, 16)) {
      range = r;
      EXPECT_TRUE(contains(line, "memfd:cast-arena")) << line;
    }
  }
  const int fd = ::open(("/proc/self/map_files/" + range).c_str(), O_RDWR | O_CLOEXEC);
  ASSERT_GE(fd, 0) << std::strerror(errno);
  const char x = 'x';
  EXPECT_EQ(::pwrite(fd, &x, 1, 0), -1);
  EXPECT_EQ(errno, EPERM);
  EXPECT_EQ(::mmap(nullptr, static_cast<std::size_t>(page), PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0), MAP_FAILED);
  ::close(fd);
  EXPECT_TRUE(view.field(1).chars() == image(kMiB, 4).value());
}

TEST(SharedMemory, ForgedAndStaleReferencesAreRefusedAndChangeNothing) {
  Raw raw(sharedServer());
  auto writer = sharedServer().connect("shm-owner", "vision");
  writer->add("shm-forged", image(kMiB, 1));
  const auto before = writer->getEntry<BytesValue>("shm-forged");
  auto session = raw.session("shm-owner");
  const cast::v1::OverwriteRequest good = stagedOverwrite(*session, "shm-forged", image(kMiB, 7));
  struct Case {
    std::string what;
    std::function<void(cast::v1::OverwriteRequest&)> change;
    std::string who;
    grpc::StatusCode code;
    std::string words;
  };
  const std::vector<Case> cases = {
      {"forged session", [](auto& r) { r.mutable_staged_value()->set_session(std::string(16, '\x07')); }, "shm-owner",
       grpc::StatusCode::INVALID_ARGUMENT, "which this server does not have"},
      {"outside", [&](auto& r) { r.mutable_staged_value()->set_offset(session->stagingBytes() - 10); }, "shm-owner",
       grpc::StatusCode::INVALID_ARGUMENT, "outside the staging area"},
      {"both", [](auto& r) { r.mutable_value()->set_value("\x0a\x01x"); }, "shm-owner",
       grpc::StatusCode::INVALID_ARGUMENT, "has both bytes"},
      {"too large", [](auto& r) { r.mutable_staged_value()->set_size(9 * kMiB); }, "shm-owner",
       grpc::StatusCode::INVALID_ARGUMENT, "limits.max_value_bytes"},
      {"another's session", [](auto&) {}, "shm-thief", grpc::StatusCode::PERMISSION_DENIED,
       "may not use the shared-memory session"},
  };
  for (const auto& c : cases) {
    cast::v1::OverwriteRequest request = good;
    c.change(request);
    const grpc::Status status = raw.overwrite(c.who, request);
    EXPECT_EQ(status.error_code(), c.code) << c.what << ": " << status.error_message();
    EXPECT_TRUE(contains(status.error_message(), c.words)) << c.what << ": " << status.error_message();
  }
  // Reads naming a session: malformed, or another component's.
  EXPECT_EQ(raw.get("shm-thief", "shm-forged", "nothex/1").error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(raw.get("shm-thief", "shm-forged", cast::detail::shm::hex(session->id()) + "/1").error_code(),
            grpc::StatusCode::PERMISSION_DENIED);
  // Stale: the session ended.
  session->close();
  ASSERT_TRUE(eventually([&] {
    const grpc::Status status = raw.overwrite("shm-owner", good);
    return status.error_code() == grpc::StatusCode::INVALID_ARGUMENT &&
           contains(status.error_message(), "which this server does not have");
  }));
  const auto after = writer->getEntry<BytesValue>("shm-forged");
  EXPECT_EQ(after.version, before.version);
  EXPECT_EQ(after.revision, before.revision);
  EXPECT_TRUE(after.value.value() == image(kMiB, 1).value());
}

TEST(SharedMemory, TurnedOffAClientGetsIdenticalValuesAsBytesAndSaysSoOnce) {
  Raw raw(sharedServer());
  auto writer = sharedServer().connect("shm-near", "vision");
  ::setenv("CAST_SHARED_MEMORY", "off", 1);
  testing::internal::CaptureStderr();
  auto remote = sharedServer().connect("shm-remote", "vision");
  std::mutex mu;
  std::vector<std::string> got;
  remote->onChange(cast::addressFilter("shm-far").withEntry(), [&](const cast::WorkingMemoryChange& change) {
    const bool shared = change.view().shared();
    std::lock_guard<std::mutex> lock(mu);
    got.push_back(shared ? "shared!" : change.entry<BytesValue>().value.value());
  });
  const auto before = raw.metrics();
  remote->add("shm-from-remote", image(kMiB, 9));
  writer->add("shm-far", image(kMiB, 1));
  ASSERT_TRUE(eventually([&] {
    std::lock_guard<std::mutex> lock(mu);
    return !got.empty();
  }));
  EXPECT_TRUE(got[0] == image(kMiB, 1).value());
  cast::ValueView view = remote->getView("shm-far");
  EXPECT_FALSE(view.shared());
  EXPECT_TRUE(view.field(1).chars() == image(kMiB, 1).value());
  remote.reset();
  const std::string said = testing::internal::GetCapturedStderr();
  ::unsetenv("CAST_SHARED_MEMORY");
  EXPECT_TRUE(writer->get<BytesValue>("shm-from-remote").value() == image(kMiB, 9).value());
  const auto after = raw.metrics();
  EXPECT_EQ(after.staged_writes() - before.staged_writes(), 1u);  // the near writer's only
  const std::string line = "shared memory with the server at " + sharedServer().endpoint() +
                           " is not used (turned off by CAST_SHARED_MEMORY=off): values travel as bytes";
  std::size_t times = 0;
  for (auto at = said.find(line); at != std::string::npos; at = said.find(line, at + 1)) ++times;
  EXPECT_EQ(times, 1u) << said;
  EXPECT_TRUE(contains(said, "INFO cast.client.shm-remote: " + line)) << said;
}

TEST(SharedMemory, ADeadServersMemoryIsUnmappedAndARestartedOneLendsAgain) {
  ASSERT_EQ(memoryFilesMapped(), 0) << "another test left a session open";
  CastServer server({"vision"});
  {
    auto writer = server.connect("shm-w", "vision");
    auto reader = server.connect("shm-r", "vision");
    std::atomic<int> lent{0};
    reader->onChange(cast::addressFilter("img").withEntry(), [&](const cast::WorkingMemoryChange& change) {
      if (change.view().shared()) ++lent;
    });
    writer->add("img", image(kMiB, 1));
    writer->overwrite("img", image(kMiB, 2));
    ASSERT_TRUE(eventually([&] { return lent == 2; }));
    EXPECT_GE(memoryFilesMapped(), 2);  // the staging areas and the segment
    server.kill();
    // Their streams to it broke: both unmap what they mapped of it.
    EXPECT_TRUE(eventually([] { return memoryFilesMapped() == 0; }, 20s)) << memoryFilesMapped();
    server.restart();
  }
  auto writer = server.connect("shm-w", "vision");
  auto reader = server.connect("shm-r", "vision");
  writer->add("img", image(kMiB, 3));
  EXPECT_TRUE(reader->getView("img").shared());
  EXPECT_TRUE(reader->get<BytesValue>("img").value() == image(kMiB, 3).value());
}

}  // namespace
