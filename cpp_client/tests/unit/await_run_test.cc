// The gRPC transport's wait at the start barrier (src/session.cc): it
// long-polls Directory.AwaitRun with a short deadline per call, calls again
// when the deadline passes or the server is away, fails on any other error,
// and gives up when the component is asked to stop. Against an in-process
// directory whose AwaitRun answers as each test scripts it.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <mutex>
#include <thread>

#include "cast/errors.h"
#include "cast/grpc_transport.h"
#include "cast/v1/directory.grpc.pb.h"
#include "transport.h"

namespace {

using namespace std::chrono_literals;
namespace v1 = cast::v1;

class ScriptedDirectory final : public v1::Directory::Service {
 public:
  grpc::Status DescribeSystem(grpc::ServerContext*, const v1::DescribeSystemRequest*,
                              v1::SystemDescription*) override {
    return grpc::Status::OK;
  }

  // Answers the next scripted status; with none left, holds the call until
  // release() or the caller's deadline.
  grpc::Status AwaitRun(grpc::ServerContext* context, const v1::AwaitRunRequest*, v1::AwaitRunResponse*) override {
    std::unique_lock<std::mutex> lock(mu_);
    ++calls;
    if (!script_.empty()) {
      grpc::Status status = script_.front();
      script_.pop_front();
      return status;
    }
    while (!released_ && !context->IsCancelled()) cv_.wait_for(lock, 10ms);
    return released_ ? grpc::Status::OK : grpc::Status(grpc::StatusCode::CANCELLED, "gone");
  }

  void script(grpc::Status status) {
    std::lock_guard<std::mutex> lock(mu_);
    script_.push_back(std::move(status));
  }
  void release() {
    {
      std::lock_guard<std::mutex> lock(mu_);
      released_ = true;
    }
    cv_.notify_all();
  }

  std::atomic<int> calls{0};

 private:
  std::mutex mu_;
  std::condition_variable cv_;
  std::deque<grpc::Status> script_;
  bool released_ = false;
};

class AwaitRun : public ::testing::Test {
 protected:
  void SetUp() override {
    grpc::ServerBuilder builder;
    int port = 0;
    builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
    builder.RegisterService(&directory);
    server = builder.BuildAndStart();
    ASSERT_NE(port, 0);
    transport = cast::connectGrpc("127.0.0.1:" + std::to_string(port), "token", {"watcher", "b", false});
  }
  void TearDown() override {
    if (transport) transport->close();
    server->Shutdown(std::chrono::system_clock::now() + 1s);
  }

  // A component never asked to stop.
  static bool neverStopped(std::chrono::milliseconds d) {
    std::this_thread::sleep_for(d);
    return false;
  }

  ScriptedDirectory directory;
  std::unique_ptr<grpc::Server> server;
  std::shared_ptr<cast::detail::Transport> transport;
};

TEST_F(AwaitRun, AReleasedBarrierAnswersAtOnce) {
  directory.release();
  EXPECT_TRUE(transport->awaitRun(neverStopped));
  EXPECT_EQ(directory.calls, 1);
}

TEST_F(AwaitRun, AfterEachDeadlineItAsksAgainUntilReleased) {
  std::thread releaser([this] {
    std::this_thread::sleep_for(2300ms);
    directory.release();
  });
  const auto began = std::chrono::steady_clock::now();
  EXPECT_TRUE(transport->awaitRun(neverStopped));
  releaser.join();
  EXPECT_GE(std::chrono::steady_clock::now() - began, 2300ms);
  EXPECT_GE(directory.calls, 3) << "one call of 1 s each, asked again after every deadline";
}

TEST_F(AwaitRun, AServerThatIsAwayIsAskedAgainWithBackoff) {
  directory.script(grpc::Status(grpc::StatusCode::UNAVAILABLE, "restarting"));
  directory.script(grpc::Status(grpc::StatusCode::UNAVAILABLE, "restarting"));
  directory.release();
  EXPECT_TRUE(transport->awaitRun(neverStopped));
  EXPECT_EQ(directory.calls, 3);
}

TEST_F(AwaitRun, AnyOtherErrorIsThrown) {
  directory.script(grpc::Status(grpc::StatusCode::PERMISSION_DENIED, "not yours"));
  EXPECT_THROW(transport->awaitRun(neverStopped), cast::PermissionDeniedError);
  EXPECT_EQ(directory.calls, 1);
}

TEST_F(AwaitRun, AStopRequestEndsTheWaitWithinOneCall) {
  std::atomic<bool> stop{false};
  auto stopping = [&](std::chrono::milliseconds d) {
    std::this_thread::sleep_for(d);
    return stop.load();
  };
  std::thread stopper([&] {
    std::this_thread::sleep_for(300ms);
    stop = true;
  });
  const auto began = std::chrono::steady_clock::now();
  EXPECT_FALSE(transport->awaitRun(stopping));
  stopper.join();
  EXPECT_LT(std::chrono::steady_clock::now() - began, 2s);
}

TEST_F(AwaitRun, AStoppedComponentDoesNotAsk) {
  directory.release();
  EXPECT_FALSE(transport->awaitRun([](std::chrono::milliseconds) { return true; }));
  EXPECT_EQ(directory.calls, 0);
}

}  // namespace
