// Component-reported outcomes (Component::report): the call reaches the
// transport as given, on a component and on a script's Connection; over
// gRPC it is Inspection.Report to the own SA's server with the token, and a
// refusal is the named error with the server's message. The aggregates a
// server keeps are checked against real servers in
// tests/interop/test_metrics_interop.py.
#include <grpcpp/grpcpp.h>
#include <gtest/gtest.h>

#include <cmath>
#include <deque>
#include <limits>
#include <mutex>

#include "cast/component.h"
#include "cast/connect.h"
#include "cast/grpc_transport.h"
#include "cast/v1/directory.grpc.pb.h"
#include "cast/v1/inspection.grpc.pb.h"
#include "fake_transport.h"

namespace {

using namespace std::chrono_literals;
using cast::testing::FakeTransport;
namespace v1 = cast::v1;

TEST(Report, AComponentReportsThroughItsTransport) {
  auto transport = std::make_shared<FakeTransport>(cast::Identity{"quizzer", "language", false});
  cast::UnmanagedComponent component;
  component.bind(transport);
  component.report("answers_correct", 1);
  component.report("answer_time_s", 0.25);
  // The server decides what is a bad value: a NaN is sent, not judged here.
  component.report("answer_time_s", std::numeric_limits<double>::quiet_NaN());
  ASSERT_EQ(transport->reports.size(), 3u);
  EXPECT_EQ(transport->reports[0], std::make_pair(std::string("answers_correct"), 1.0));
  EXPECT_EQ(transport->reports[1], std::make_pair(std::string("answer_time_s"), 0.25));
  EXPECT_TRUE(std::isnan(transport->reports[2].second));
  component.close();
}

TEST(Report, ARefusalIsTheNamedErrorWithTheServersMessage) {
  auto transport = std::make_shared<FakeTransport>(cast::Identity{"quizzer", "language", false});
  cast::UnmanagedComponent component;
  component.bind(transport);
  transport->reportError = std::make_shared<cast::ResourceExhaustedError>("too many names");
  try {
    component.report("one-too-many", 1);
    FAIL() << "no error";
  } catch (const cast::ResourceExhaustedError& e) {
    EXPECT_EQ(e.message(), "too many names");
  }
  component.close();
}

TEST(Report, AnUnboundComponentSaysHowToRunIt) {
  cast::UnmanagedComponent component;
  EXPECT_THROW(component.report("answers_correct", 1), cast::CastError);
}

TEST(Report, AScriptsConnectionReportsToo) {
  auto transport = std::make_shared<FakeTransport>(cast::Identity{"script-x", "vision", true});
  auto wm = cast::connect(transport);
  wm->report("done", 2);
  ASSERT_EQ(transport->reports.size(), 1u);
  EXPECT_EQ(transport->reports[0], std::make_pair(std::string("done"), 2.0));
}

// ------------------------------------------------------------ over gRPC

// A directory that describes nothing (every SA goes to this server) and an
// Inspection whose Report records the request and answers as scripted.
class ScriptedDirectory final : public v1::Directory::Service {
 public:
  grpc::Status DescribeSystem(grpc::ServerContext*, const v1::DescribeSystemRequest*,
                              v1::SystemDescription*) override {
    return grpc::Status::OK;
  }
};

class ScriptedInspection final : public v1::Inspection::Service {
 public:
  grpc::Status Report(grpc::ServerContext* context, const v1::ReportRequest* request, v1::ReportResponse*) override {
    std::lock_guard<std::mutex> lock(mu);
    auto auth = context->client_metadata().find("authorization");
    authorization = auth == context->client_metadata().end() ? "" : std::string(auth->second.data(), auth->second.size());
    requests.push_back(*request);
    if (answers.empty()) return grpc::Status::OK;
    grpc::Status status = answers.front();
    answers.pop_front();
    return status;
  }

  std::mutex mu;
  std::deque<grpc::Status> answers;
  std::vector<v1::ReportRequest> requests;
  std::string authorization;
};

class GrpcReport : public ::testing::Test {
 protected:
  void SetUp() override {
    grpc::ServerBuilder builder;
    int port = 0;
    builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(), &port);
    builder.RegisterService(&directory);
    builder.RegisterService(&inspection);
    server = builder.BuildAndStart();
    ASSERT_NE(port, 0);
    transport = cast::connectGrpc("127.0.0.1:" + std::to_string(port), "the-token", {"quizzer", "language", false});
  }
  void TearDown() override {
    if (transport) transport->close();
    server->Shutdown(std::chrono::system_clock::now() + 1s);
  }

  ScriptedDirectory directory;
  ScriptedInspection inspection;
  std::unique_ptr<grpc::Server> server;
  std::shared_ptr<cast::detail::Transport> transport;
};

TEST_F(GrpcReport, ItSendsTheNameAndValueWithTheToken) {
  transport->report("answer_time_s", 1.5);
  std::lock_guard<std::mutex> lock(inspection.mu);
  ASSERT_EQ(inspection.requests.size(), 1u);
  EXPECT_EQ(inspection.requests[0].name(), "answer_time_s");
  EXPECT_EQ(inspection.requests[0].value(), 1.5);
  EXPECT_EQ(inspection.authorization, "Bearer the-token");
}

TEST_F(GrpcReport, InvalidArgumentAndResourceExhaustedAreTheirNamedErrors) {
  {
    std::lock_guard<std::mutex> lock(inspection.mu);
    inspection.answers.emplace_back(grpc::StatusCode::INVALID_ARGUMENT,
                                    "report 'x': the value must be a finite number, got nan");
    inspection.answers.emplace_back(grpc::StatusCode::RESOURCE_EXHAUSTED, "already reports 256 names");
  }
  try {
    transport->report("x", std::numeric_limits<double>::quiet_NaN());
    FAIL() << "no error";
  } catch (const cast::InvalidArgumentError& e) {
    EXPECT_EQ(e.message(), "report 'x': the value must be a finite number, got nan");
  }
  EXPECT_THROW(transport->report("y", 1), cast::ResourceExhaustedError);
  std::lock_guard<std::mutex> lock(inspection.mu);
  ASSERT_EQ(inspection.requests.size(), 2u);
  EXPECT_TRUE(std::isnan(inspection.requests[0].value()));
}

}  // namespace
