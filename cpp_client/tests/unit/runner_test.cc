// The launch contract and token reading of the runner.
#include <gtest/gtest.h>

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

TEST(LaunchContract, NamesEveryMissingVariable) {
  auto env = fullEnv();
  env.erase("CAST_TOKEN");
  env["CAST_ENDPOINT"] = "";
  try {
    cast::LaunchContract::fromEnv(env);
    FAIL() << "no error";
  } catch (const cast::InvalidArgumentError& e) {
    EXPECT_NE(e.message().find("missing launch environment: CAST_ENDPOINT, CAST_TOKEN;"), std::string::npos)
        << e.message();
  }
}

TEST(LaunchContract, ArgsAreOptionalButMustBeAnObject) {
  auto env = fullEnv();
  env.erase("CAST_ARGS");
  EXPECT_TRUE(cast::LaunchContract::fromEnv(env).args.keys().empty());
  env["CAST_ARGS"] = "[1]";
  EXPECT_THROW(cast::LaunchContract::fromEnv(env), cast::InvalidArgumentError);
}

// Tokens as cast.auth.TokenSigner writes them: base64url(JSON).base64url(HMAC).
TEST(Tokens, PeekReadsTheClaimsWithoutVerifying) {
  // {"c":"planner","exp":0,"iat":1700000000,"p":true,"s":"coordination"}
  const std::string token =
      "eyJjIjoicGxhbm5lciIsImV4cCI6MCwiaWF0IjoxNzAwMDAwMDAwLCJwIjp0cnVlLCJzIjoiY29vcmRpbmF0aW9uIn0.c2ln";
  auto id = cast::peekToken(token);
  ASSERT_TRUE(id.has_value());
  EXPECT_EQ(id->componentId, "planner");
  EXPECT_EQ(id->subarchitecture, "coordination");
  EXPECT_TRUE(id->privileged);

  auto env = fullEnv();
  env["CAST_TOKEN"] = token;
  EXPECT_TRUE(cast::LaunchContract::fromEnv(env).identity().privileged);
}

TEST(Tokens, GarbageIsNotAToken) {
  EXPECT_EQ(cast::peekToken("no-dot-here"), std::nullopt);
  EXPECT_EQ(cast::peekToken("!!!.x"), std::nullopt);
  EXPECT_EQ(cast::peekToken("bm90IGpzb24.x"), std::nullopt);  // "not json"
  EXPECT_FALSE(cast::LaunchContract::fromEnv(fullEnv()).identity().privileged);
}

}  // namespace
