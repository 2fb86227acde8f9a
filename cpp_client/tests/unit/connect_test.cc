// cast::connect for scripts: how it finds the endpoint, token and TLS
// (environment, runtime directory, minting from the secret), and a
// Connection's calls over the in-memory transport.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cstdlib>
#include <fstream>
#include <functional>
#include <future>

#include "cast/connect.h"
#include "cast/credentials.h"
#include "cast_testing.pb.h"
#include "connect_resolve.h"
#include "fake_transport.h"
#include "jwt.h"
#include "test_tokens.h"

namespace {

using namespace std::chrono_literals;
using Env = std::map<std::string, std::string>;

using cast::unit::kPlannerToken;
using cast::unit::kSecret;

// A runtime directory of the test's own, removed at the end.
class RuntimeDir {
 public:
  RuntimeDir() {
    char pattern[] = "/tmp/cast-connect-test-XXXXXX";
    path = ::mkdtemp(pattern);
  }
  ~RuntimeDir() { std::system(("rm -rf '" + path + "'").c_str()); }
  std::string write(const std::string& name, const std::string& text) const {
    std::ofstream(path + "/" + name) << text;
    return path + "/" + name;
  }
  // A system.json as a running `cast run` (this process) writes it.
  void system(const std::string& extra = "", long pid = static_cast<long>(::getpid())) const {
    write("system.json", R"({"system": "test", "endpoint": "127.0.0.1:7001",
      "servers": {"zeta": {"endpoint": "127.0.0.1:7001", "subarchitectures": ["motor", "vision"]},
                  "alpha": {"endpoint": "127.0.0.1:7002", "subarchitectures": ["language"]}},
      "pid": )" + std::to_string(pid) + R"(, "config": "system.yaml")" + extra + "}");
  }
  std::string path;
};

cast::ConnectOptions inDir(const RuntimeDir& dir) {
  cast::ConnectOptions options;
  options.runtimeDir = dir.path;
  return options;
}

// The message of the error E that fn throws (another error fails the test).
template <class E = cast::InvalidArgumentError>
std::string errorOf(const std::function<void()>& fn) {
  try {
    fn();
  } catch (const E& e) {
    return e.message();
  }
  return "(no such error)";
}

// The parts of a JWT.
std::vector<std::string> parts(const std::string& token) {
  std::vector<std::string> out;
  std::size_t start = 0;
  for (std::size_t dot; (dot = token.find('.', start)) != std::string::npos; start = dot + 1) {
    out.push_back(token.substr(start, dot - start));
  }
  out.push_back(token.substr(start));
  return out;
}

// ------------------------------------------------------------ the endpoint

TEST(ConnectResolve, EndpointFromTheOptionThenTheEnvironmentThenSystemJson) {
  RuntimeDir dir;
  dir.system();
  auto options = inDir(dir);
  options.token = kPlannerToken;
  EXPECT_EQ(cast::detail::resolveConnect(options, {}, 0).endpoint, "127.0.0.1:7001");
  EXPECT_EQ(cast::detail::resolveConnect(options, {{"CAST_ENDPOINT", "env:1"}}, 0).endpoint, "env:1");
  options.endpoint = "option:2";
  EXPECT_EQ(cast::detail::resolveConnect(options, {{"CAST_ENDPOINT", "env:1"}}, 0).endpoint, "option:2");
}

TEST(ConnectResolve, TheRuntimeDirComesFromTheEnvironmentToo) {
  RuntimeDir dir;
  dir.system();
  cast::ConnectOptions options;
  options.token = kPlannerToken;
  EXPECT_EQ(cast::detail::resolveConnect(options, {{"CAST_RUNTIME_DIR", dir.path}}, 0).endpoint, "127.0.0.1:7001");
}

TEST(ConnectResolve, NoSystemSaysWhatToGive) {
  RuntimeDir dir;
  auto options = inDir(dir);
  const std::string message = errorOf<cast::NotFoundError>([&] { cast::detail::resolveConnect(options, {}, 0); });
  EXPECT_NE(message.find("no CAST system to connect to: there is no " + dir.path + "/system.json"), std::string::npos)
      << message;
  EXPECT_NE(message.find("`cast run CONFIG`"), std::string::npos) << message;
  EXPECT_NE(message.find("ConnectOptions::endpoint (or CAST_ENDPOINT)"), std::string::npos) << message;
}

TEST(ConnectResolve, SystemJsonOfAProcessThatIsGoneIsIgnored) {
  RuntimeDir dir;
  dir.system("", 999999999);  // above any pid_max
  const std::string message =
      errorOf<cast::NotFoundError>([&] { cast::detail::resolveConnect(inDir(dir), {}, 0); });
  EXPECT_NE(message.find("was written by process 999999999, which is no longer running"), std::string::npos)
      << message;
}

// ------------------------------------------------------------ given tokens

TEST(ConnectResolve, TokenFromTheOptionThenTheTokenFileThenTheEnvironment) {
  RuntimeDir dir;
  dir.system();
  const std::string worker = cast::mintToken(kSecret, {"worker", "vision", false}, 1);
  const std::string file = dir.write("worker.token", worker + "\n");
  Env env{{"CAST_TOKEN_FILE", file}, {"CAST_TOKEN", kPlannerToken}};

  auto plan = cast::detail::resolveConnect(inDir(dir), env, 0);
  EXPECT_EQ(plan.token, worker);
  EXPECT_EQ(plan.tokenFile, file);  // renewed tokens are picked up from there
  EXPECT_EQ(plan.identity.componentId, "worker");
  EXPECT_EQ(plan.identity.subarchitecture, "vision");
  EXPECT_FALSE(plan.identity.privileged);

  env.erase("CAST_TOKEN_FILE");
  plan = cast::detail::resolveConnect(inDir(dir), env, 0);
  EXPECT_EQ(plan.token, kPlannerToken);
  EXPECT_EQ(plan.tokenFile, "");
  EXPECT_EQ(plan.identity.componentId, "planner");
  EXPECT_TRUE(plan.identity.privileged);

  auto options = inDir(dir);
  options.token = worker;
  EXPECT_EQ(cast::detail::resolveConnect(options, env, 0).identity.componentId, "worker");
}

TEST(ConnectResolve, ATokenThatCannotBeUsedIsNamed) {
  RuntimeDir dir;
  dir.system();
  EXPECT_NE(errorOf([&] { cast::detail::resolveConnect(inDir(dir), {{"CAST_TOKEN_FILE", dir.path + "/none"}}, 0); })
                .find("CAST_TOKEN_FILE names " + dir.path + "/none, which cannot be read"),
            std::string::npos);
  const std::string oldFormat = errorOf<cast::UnauthenticatedError>(
      [&] { cast::detail::resolveConnect(inDir(dir), {{"CAST_TOKEN", "eyJjIjoicCJ9.c2ln"}}, 0); });
  EXPECT_NE(oldFormat.find("the token from CAST_TOKEN is not a CAST token (it has the format before JWTs)"),
            std::string::npos)
      << oldFormat;
  auto options = inDir(dir);
  options.token = kPlannerToken;
  options.subarchitecture = "vision";
  const std::string conflict = errorOf([&] { cast::detail::resolveConnect(options, {}, 0); });
  EXPECT_NE(conflict.find("ConnectOptions::subarchitecture is 'vision' but the token from ConnectOptions::token is "
                          "for 'coordination'"),
            std::string::npos)
      << conflict;
}

// ------------------------------------------------------------ minted tokens

TEST(ConnectResolve, MintsAPrivilegedTokenFromTheRuntimeDirsSecret) {
  RuntimeDir dir;
  dir.system();
  dir.write("secret", kSecret + "\n");
  auto plan = cast::detail::resolveConnect(inDir(dir), {}, 1700000123);
  EXPECT_EQ(plan.identity.componentId, "script-" + [] {
    char host[256] = {};
    ::gethostname(host, sizeof host - 1);
    return std::string(host);
  }() + "-" + std::to_string(::getpid()));
  EXPECT_EQ(plan.identity.subarchitecture, "motor");  // the first SA of the first server, in the file's order
  EXPECT_TRUE(plan.identity.privileged);
  // The token verifies with the secret: its signature is HS256 over header.payload.
  auto p = parts(plan.token);
  ASSERT_EQ(p.size(), 3u);
  EXPECT_EQ(p[0], "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9");  // {"alg":"HS256","typ":"JWT"}
  EXPECT_EQ(p[2], cast::detail::signHs256(p[0] + "." + p[1], kSecret));
  EXPECT_EQ(*cast::detail::base64UrlDecode(p[1]),
            "{\"c\":\"" + plan.identity.componentId + "\",\"s\":\"motor\",\"p\":true,\"iat\":1700000123}");
  EXPECT_EQ(plan.tokenFile, "");
}

TEST(ConnectResolve, TheSecretComesFromTheEnvironmentFirst) {
  RuntimeDir dir;
  dir.system();
  dir.write("secret", "the-runtime-dirs-secret-is-not-used-here");
  auto options = inDir(dir);
  options.componentId = "notebook";
  options.subarchitecture = "language";
  const std::string other = "another-secret-0123456789abcdef-0123456789";
  const std::string file = dir.write("other.secret", "  " + other + "\n");

  auto plan = cast::detail::resolveConnect(options, {{"CAST_SECRET", kSecret}, {"CAST_SECRET_FILE", file}}, 5);
  EXPECT_EQ(plan.token, cast::mintToken(kSecret, {"notebook", "language", true}, 5));
  plan = cast::detail::resolveConnect(options, {{"CAST_SECRET_FILE", file}}, 5);
  EXPECT_EQ(plan.token, cast::mintToken(other, {"notebook", "language", true}, 5));
  EXPECT_EQ(plan.identity.componentId, "notebook");
}

TEST(ConnectResolve, MintingNeedsASubarchitectureAndASecret) {
  RuntimeDir dir;
  auto options = inDir(dir);
  options.endpoint = "127.0.0.1:7001";
  const std::string noSecret = errorOf<cast::NotFoundError>([&] { cast::detail::resolveConnect(options, {}, 0); });
  EXPECT_NE(noSecret.find("no token and no secret to mint one: give ConnectOptions::token"), std::string::npos)
      << noSecret;
  EXPECT_NE(noSecret.find(dir.path + "/secret"), std::string::npos) << noSecret;

  const std::string noSa = errorOf([&] { cast::detail::resolveConnect(options, {{"CAST_SECRET", kSecret}}, 0); });
  EXPECT_NE(noSa.find("give ConnectOptions::subarchitecture"), std::string::npos) << noSa;

  options.subarchitecture = "vision";
  const std::string shortSecret = errorOf([&] { cast::detail::resolveConnect(options, {{"CAST_SECRET", "abc"}}, 0); });
  EXPECT_NE(shortSecret.find("the secret from CAST_SECRET: the token secret is 3 bytes"), std::string::npos)
      << shortSecret;
}

// ------------------------------------------------------------ TLS

TEST(ConnectResolve, TlsFromTheOptionThenTheEnvironmentThenSystemJson) {
  RuntimeDir dir;
  dir.system(R"(, "tls": {"ca": "/pki/ca.pem", "cert": "/pki/client.pem", "key": "/pki/client.key"})");
  auto options = inDir(dir);
  options.token = kPlannerToken;
  auto tls = cast::detail::resolveConnect(options, {}, 0).tls;
  ASSERT_TRUE(tls.has_value());
  EXPECT_EQ(tls->ca, "/pki/ca.pem");
  EXPECT_EQ(tls->cert, "/pki/client.pem");
  EXPECT_EQ(tls->key, "/pki/client.key");

  tls = cast::detail::resolveConnect(options, {{"CAST_TLS_CA", "env-ca.pem"}, {"CAST_TLS_SERVER_NAME", "wm"}}, 0).tls;
  EXPECT_EQ(tls->ca, "env-ca.pem");
  EXPECT_EQ(tls->cert, "");
  EXPECT_EQ(tls->serverName, "wm");

  options.tls = cast::ClientTls{"option-ca.pem", "", "", ""};
  EXPECT_EQ(cast::detail::resolveConnect(options, {{"CAST_TLS_CA", "env-ca.pem"}}, 0).tls->ca, "option-ca.pem");
  options.tls = cast::ClientTls{"option-ca.pem", "client.pem", "", ""};
  EXPECT_NE(errorOf([&] { cast::detail::resolveConnect(options, {}, 0); }).find("give both cert and key"),
            std::string::npos);

  dir.system(R"(, "tls": null)");
  options.tls.reset();
  EXPECT_FALSE(cast::detail::resolveConnect(options, {}, 0).tls.has_value());
}

// ------------------------------------------------------------ the Connection

TEST(Connection, HasTheCallsOfAComponentAndEndsItsSessionOnClose) {
  auto transport = std::make_shared<cast::testing::FakeTransport>(cast::Identity{"script-x", "vision", true});
  auto wm = cast::connect(transport);
  EXPECT_EQ(wm->componentId(), "script-x");
  EXPECT_EQ(wm->subarchitecture(), "vision");
  EXPECT_TRUE(wm->privileged());
  EXPECT_EQ(transport->sessionKind, "unmanaged");
  EXPECT_EQ(transport->reportedState(), cast::ComponentState::Running);

  std::promise<std::string> seen;
  auto watch = wm->onChange(cast::localTypeFilter<cast::testing::Counter>({cast::Operation::Add}, true),
                            [&](const cast::WorkingMemoryChange& change) {
                              seen.set_value(change.entry<cast::testing::Counter>().value.writer());
                            });
  cast::testing::Counter counter;
  counter.set_writer("script");
  const std::string id = wm->newId();
  EXPECT_EQ(id.rfind("script-x:", 0), 0u) << id;
  wm->add(id, counter);
  EXPECT_EQ(wm->get<cast::testing::Counter>(id).writer(), "script");
  EXPECT_TRUE(wm->exists(id));
  auto future = seen.get_future();
  ASSERT_EQ(future.wait_for(5s), std::future_status::ready);
  EXPECT_EQ(future.get(), "script");
  {
    auto guard = wm->lock(id, cast::LockMode::O);
    EXPECT_EQ(transport->lockDepth("vision", id), 1u);
  }
  EXPECT_EQ(transport->lockDepth("vision", id), 0u);
  wm->deleteEntry(id);
  EXPECT_FALSE(wm->exists(id));

  wm.reset();  // destroying it closes the session
  EXPECT_TRUE(transport->closed);
}

TEST(Connection, CallsAfterCloseSayTheSessionEnded) {
  auto transport = std::make_shared<cast::testing::FakeTransport>(cast::Identity{"script-x", "vision", true});
  auto wm = cast::connect(transport);
  wm->close();
  try {
    wm->exists("x");
    FAIL() << "no error";
  } catch (const cast::CastError& e) {
    EXPECT_NE(e.message().find("closed"), std::string::npos) << e.message();
  }
}

}  // namespace
