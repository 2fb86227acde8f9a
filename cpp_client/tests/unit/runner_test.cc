// The launch contract of the runner: what it reads from the environment.
#include <gtest/gtest.h>

#include <cstdio>
#include <fstream>

#include "cast/runner.h"

namespace {

std::map<std::string, std::string> fullEnv() {
  return {{"CAST_ENDPOINT", "127.0.0.1:5555"},
          {"CAST_COMPONENT_ID", "segmenter"},
          {"CAST_SUBARCHITECTURE", "vision"},
          {"CAST_TOKEN", "abc.def"},
          {"CAST_ARGS", R"({"rate_hz": 20})"}};
}

TEST(LaunchContract, ReadsTheEnvironment) {
  auto c = cast::LaunchContract::fromEnv(fullEnv());
  EXPECT_EQ(c.endpoint, "127.0.0.1:5555");
  EXPECT_EQ(c.componentId, "segmenter");
  EXPECT_EQ(c.subarchitecture, "vision");
  EXPECT_EQ(c.token, "abc.def");
  EXPECT_EQ(c.args.getInt("rate_hz"), 20);
}

std::string errorOf(const std::map<std::string, std::string>& env) {
  try {
    cast::LaunchContract::fromEnv(env);
  } catch (const cast::InvalidArgumentError& e) {
    return e.message();
  }
  return "no error";
}

TEST(LaunchContract, NamesEveryMissingVariable) {
  auto env = fullEnv();
  env.erase("CAST_TOKEN");
  env["CAST_ENDPOINT"] = "";
  EXPECT_EQ(errorOf(env).rfind("missing launch environment: CAST_ENDPOINT, CAST_TOKEN or CAST_TOKEN_FILE; start", 0),
            0u)
      << errorOf(env);
}

// The file is the renewed token: set, it is the token (CAST_TOKEN may be
// absent, as in an exported pod), and it wins over CAST_TOKEN, as for
// cast::connect (connect_test.cc). Empty or unreadable, it is named, not
// passed over. A real runner: tests/interop/test_cpp_session.py.
TEST(LaunchContract, TheTokenFileIsTheTokenWhenSet) {
  const std::string path = ::testing::TempDir() + "cast_runner_test.token";
  std::ofstream(path) << "\n  file.token \n";
  auto env = fullEnv();
  env.erase("CAST_TOKEN");
  env["CAST_TOKEN_FILE"] = path;
  auto contract = cast::LaunchContract::fromEnv(env);
  EXPECT_EQ(contract.token, "file.token");
  EXPECT_EQ(contract.tokenFile, path);
  env["CAST_TOKEN"] = "stale.token";
  EXPECT_EQ(cast::LaunchContract::fromEnv(env).token, "file.token");
  std::ofstream(path) << " \n";
  EXPECT_EQ(errorOf(env), "CAST_TOKEN_FILE names " + path +
                              ", which is empty: point it at a token file (`cast run` renews one per component), "
                              "or unset it");
  std::remove(path.c_str());
  EXPECT_EQ(errorOf(env).rfind("CAST_TOKEN_FILE names " + path + ", which cannot be read: point it at", 0), 0u)
      << errorOf(env);
  env["CAST_TOKEN_FILE"] = ::testing::TempDir();  // a directory: as in Python and Java, not "is empty"
  EXPECT_EQ(errorOf(env).rfind("CAST_TOKEN_FILE names " + ::testing::TempDir() + ", which cannot be read", 0), 0u)
      << errorOf(env);
}

TEST(LaunchContract, ArgsAreOptionalButMustBeAnObject) {
  auto env = fullEnv();
  env.erase("CAST_ARGS");
  EXPECT_TRUE(cast::LaunchContract::fromEnv(env).args.keys().empty());
  env["CAST_ARGS"] = "[1]";
  EXPECT_THROW(cast::LaunchContract::fromEnv(env), cast::InvalidArgumentError);
}

TEST(LaunchContract, TlsIsPartOfIt) {
  std::map<std::string, std::string> env = {{"CAST_ENDPOINT", "h:1"},
                                            {"CAST_COMPONENT_ID", "c"},
                                            {"CAST_SUBARCHITECTURE", "s"},
                                            {"CAST_TOKEN", "t"},
                                            {"CAST_TLS_CA", "ca.pem"}};
  auto contract = cast::LaunchContract::fromEnv(env);
  ASSERT_TRUE(contract.tls.has_value());
  EXPECT_EQ(contract.tls->ca, "ca.pem");
  env["CAST_TLS_KEY"] = "k.pem";
  EXPECT_THROW(cast::LaunchContract::fromEnv(env), cast::InvalidArgumentError);
}

// `cast run` sets CAST_START_BARRIER=1; started any other way, run() follows
// start() at once (start_barrier_test.cc).
TEST(LaunchContract, TheStartBarrierIsOnlyForWhatCastRunLaunched) {
  auto env = fullEnv();
  EXPECT_FALSE(cast::LaunchContract::fromEnv(env).startBarrier);
  env["CAST_START_BARRIER"] = "1";
  EXPECT_TRUE(cast::LaunchContract::fromEnv(env).startBarrier);
  env["CAST_START_BARRIER"] = "0";
  EXPECT_FALSE(cast::LaunchContract::fromEnv(env).startBarrier);
}

// The contract does not decode the token: its identity is the environment's,
// and the privilege comes from the server at Register (session_test.cc).
TEST(LaunchContract, TheIdentityIsTheEnvironmentsNotTheTokens) {
  auto env = fullEnv();
  // PyJWT: {"c": "planner", "s": "coordination", "p": true, "iat": 1700000000, "exp": 1700003600}.
  env["CAST_TOKEN"] =
      "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9."
      "eyJjIjoicGxhbm5lciIsInMiOiJjb29yZGluYXRpb24iLCJwIjp0cnVlLCJpYXQiOjE3MDAwMDAwMDAsImV4cCI6MTcwMDAwMzYwMH0."
      "mON1cpsY000YjhzfewPiFgGFw69BHVWWsbe6zfS8uGs";
  const cast::Identity identity = cast::LaunchContract::fromEnv(env).identity();
  EXPECT_EQ(identity.componentId, "segmenter");
  EXPECT_EQ(identity.subarchitecture, "vision");
  EXPECT_FALSE(identity.privileged);
}

}  // namespace
