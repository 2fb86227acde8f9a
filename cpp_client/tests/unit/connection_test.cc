// The optional parts of the launch contract: TLS settings and renewed tokens.
#include <gtest/gtest.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <thread>

#include "cast/grpc_transport.h"
#include "cast/runner.h"

namespace {

using namespace std::chrono_literals;

TEST(ClientTls, AbsentMeansPlaintext) { EXPECT_EQ(cast::ClientTls::fromEnv({}), std::nullopt); }

TEST(ClientTls, ReadsEverySetting) {
  auto tls = cast::ClientTls::fromEnv({{"CAST_TLS_CA", "ca.pem"},
                                       {"CAST_TLS_CERT", "c.pem"},
                                       {"CAST_TLS_KEY", "k.pem"},
                                       {"CAST_TLS_SERVER_NAME", "wm.example"}});
  ASSERT_TRUE(tls.has_value());
  EXPECT_EQ(tls->ca, "ca.pem");
  EXPECT_EQ(tls->cert, "c.pem");
  EXPECT_EQ(tls->key, "k.pem");
  EXPECT_EQ(tls->serverName, "wm.example");
}

TEST(ClientTls, IncompleteSettingsSayWhatIsMissing) {
  try {
    cast::ClientTls::fromEnv({{"CAST_TLS_CERT", "c.pem"}, {"CAST_TLS_KEY", "k.pem"}});
    FAIL() << "no error";
  } catch (const cast::InvalidArgumentError& e) {
    EXPECT_NE(e.message().find("set the CA too"), std::string::npos) << e.message();
  }
  try {
    cast::ClientTls::fromEnv({{"CAST_TLS_CA", "ca.pem"}, {"CAST_TLS_CERT", "c.pem"}});
    FAIL() << "no error";
  } catch (const cast::InvalidArgumentError& e) {
    EXPECT_NE(e.message().find("both"), std::string::npos) << e.message();
  }
}

TEST(ClientTls, IsPartOfTheLaunchContract) {
  std::map<std::string, std::string> env = {{"CAST_ENDPOINT", "h:1"},
                                            {"CAST_COMPONENT_ID", "c"},
                                            {"CAST_SUBARCHITECTURE", "s"},
                                            {"CAST_TOKEN", "t"},
                                            {"CAST_TOKEN_FILE", "/run/c.token"},
                                            {"CAST_TLS_CA", "ca.pem"}};
  auto contract = cast::LaunchContract::fromEnv(env);
  EXPECT_EQ(contract.tokenFile, "/run/c.token");
  ASSERT_TRUE(contract.tls.has_value());
  EXPECT_EQ(contract.tls->ca, "ca.pem");
  env["CAST_TLS_KEY"] = "k.pem";
  EXPECT_THROW(cast::LaunchContract::fromEnv(env), cast::InvalidArgumentError);
}

class TokenFile : public ::testing::Test {
 protected:
  void SetUp() override {
    char name[] = "/tmp/cast-token-XXXXXX";
    int fd = ::mkstemp(name);
    ASSERT_GE(fd, 0);
    ::close(fd);
    path_ = name;
  }
  void TearDown() override { std::remove(path_.c_str()); }
  // Replaces the file as the orchestrator does: write aside, then rename.
  void write(const std::string& text) {
    const std::string tmp = path_ + ".tmp";
    std::ofstream(tmp) << text;
    std::rename(tmp.c_str(), path_.c_str());
  }
  std::string path_;
};

TEST_F(TokenFile, AFixedTokenNeverChanges) {
  cast::TokenSource tokens("fixed");
  EXPECT_EQ(tokens.token(), "fixed");
  EXPECT_FALSE(tokens.refresh());
}

TEST_F(TokenFile, TheFileWinsOverTheInitialToken) {
  write("from-file\n");
  cast::TokenSource tokens("initial", path_, 0ms);
  EXPECT_EQ(tokens.token(), "from-file");
}

TEST_F(TokenFile, ARenewedFileIsReadAgain) {
  write("first\n");
  cast::TokenSource tokens("first", path_, 0ms);
  EXPECT_EQ(tokens.token(), "first");
  std::this_thread::sleep_for(10ms);  // a new modification time
  write("second-and-longer\n");
  EXPECT_EQ(tokens.token(), "second-and-longer");
  EXPECT_FALSE(tokens.refresh()) << "nothing changed since";
  std::this_thread::sleep_for(10ms);
  write("third\n");
  EXPECT_TRUE(tokens.refresh());
  EXPECT_EQ(tokens.token(), "third");
}

TEST_F(TokenFile, TheFileIsCheckedAtMostEveryInterval) {
  write("first\n");
  cast::TokenSource tokens("first", path_, 60000ms);
  std::this_thread::sleep_for(10ms);
  write("second\n");
  EXPECT_EQ(tokens.token(), "first") << "checked again before the interval passed";
  EXPECT_TRUE(tokens.refresh()) << "refresh() reads it at once";
  EXPECT_EQ(tokens.token(), "second");
}

TEST_F(TokenFile, AnEmptyOrMissingFileKeepsTheLastToken) {
  write("good\n");
  cast::TokenSource tokens("initial", path_, 0ms);
  std::this_thread::sleep_for(10ms);
  write("");
  EXPECT_EQ(tokens.token(), "good");
  std::remove(path_.c_str());
  EXPECT_EQ(tokens.token(), "good");
  EXPECT_FALSE(tokens.refresh());
}

}  // namespace
