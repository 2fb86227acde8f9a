// Credentials (cast/credentials.h): tokens are JWTs (HS256), read and minted
// byte for byte as cast.auth.TokenSigner (PyJWT) does; a token file renewed by
// the orchestrator; the TLS settings of the launch contract.
#include <gtest/gtest.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <thread>

#include "cast/credentials.h"
#include "cast/errors.h"
#include "cast/grpc_transport.h"
#include "jwt.h"
#include "test_tokens.h"

namespace {

using namespace std::chrono_literals;

using cast::unit::kPlannerToken;
using cast::unit::kSecret;

TEST(Tokens, PeekReadsTheClaimsOfTheSecondPart) {
  auto id = cast::peekToken(kPlannerToken);
  ASSERT_TRUE(id.has_value());
  EXPECT_EQ(id->componentId, "planner");
  EXPECT_EQ(id->subarchitecture, "coordination");
  EXPECT_TRUE(id->privileged);
}

TEST(Tokens, PeekRefusesWhatIsNoJwtOfOurs) {
  EXPECT_EQ(cast::peekToken("no-dot-here"), std::nullopt);
  // The format before JWTs, base64url(claims).signature: the claims are not where a JWT has them.
  EXPECT_EQ(cast::peekToken("eyJjIjoicCIsInMiOiJ2IiwicCI6dHJ1ZX0.c2ln"), std::nullopt);
  EXPECT_EQ(cast::peekToken("eyJhbGciOiJIUzI1NiJ9.!!!.sig"), std::nullopt);
  EXPECT_EQ(cast::peekToken("eyJhbGciOiJIUzI1NiJ9.bm90IGpzb24.sig"), std::nullopt);  // "not json"
  // {"c":"p","s":"v"}: no "p" claim.
  EXPECT_EQ(cast::peekToken("eyJhbGciOiJIUzI1NiJ9.eyJjIjoicCIsInMiOiJ2In0.sig"), std::nullopt);
  EXPECT_EQ(cast::peekToken(kPlannerToken + ".extra"), std::nullopt);
}

TEST(Tokens, Hs256MatchesAKnownVector) {
  // The example of jwt.io (RFC 7519's header and claims, secret "your-256-bit-secret").
  EXPECT_EQ(cast::detail::signHs256("eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9."
                                    "eyJzdWIiOiIxMjM0NTY3ODkwIiwibmFtZSI6IkpvaG4gRG9lIiwiaWF0IjoxNTE2MjM5MDIyfQ",
                                    "your-256-bit-secret"),
            "SflKxwRJSMeKKF2QT4fwpMeJf36POk6yJV_adQssw5c");
}

TEST(Tokens, MintedTokensAreThoseTheServerIssues) {
  // PyJWT: jwt.encode({"c": "script-host-42", "s": "vision", "p": True, "iat": 1700000000}, kSecret, "HS256").
  EXPECT_EQ(cast::mintToken(kSecret, {"script-host-42", "vision", true}, 1700000000),
            "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9."
            "eyJjIjoic2NyaXB0LWhvc3QtNDIiLCJzIjoidmlzaW9uIiwicCI6dHJ1ZSwiaWF0IjoxNzAwMDAwMDAwfQ."
            "GV9K--yQT7Hfsi6RLHqlQeHX0ueUeZ6KSM-C3i3AQIk");
  EXPECT_EQ(cast::mintToken(kSecret, {"worker", "vision", false}, 1700000000),
            "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9."
            "eyJjIjoid29ya2VyIiwicyI6InZpc2lvbiIsInAiOmZhbHNlLCJpYXQiOjE3MDAwMDAwMDB9."
            "be7w-IN7v4b7UGcmj70cE90WGKwP6lZcQm1wWFs03v0");
  // Quotes, backslashes and control characters are escaped as json.dumps escapes them.
  const std::string odd = cast::mintToken(kSecret, {"a \"quoted\" \\ id\n", "vision", true}, 1700000000);
  EXPECT_EQ(odd,
            "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9."
            "eyJjIjoiYSBcInF1b3RlZFwiIFxcIGlkXG4iLCJzIjoidmlzaW9uIiwicCI6dHJ1ZSwiaWF0IjoxNzAwMDAwMDAwfQ."
            "8_nm3PI22a7mqz0tm6WHCR9nmdfGFnHYpWC9iaSRNFo");
  EXPECT_EQ(cast::peekToken(odd)->componentId, "a \"quoted\" \\ id\n");
}

TEST(Tokens, MintingWithAShortSecretSaysWhy) {
  try {
    cast::mintToken("short", {"x", "vision", true}, 1);
    FAIL() << "no error";
  } catch (const cast::InvalidArgumentError& e) {
    EXPECT_NE(e.message().find("5 bytes, shorter than 32"), std::string::npos) << e.message();
  }
}

TEST(Tokens, Base64UrlRoundTrips) {
  for (const std::string& bytes : {std::string(""), std::string("f"), std::string("fo"), std::string("foo"),
                                   std::string("\xff\xfe\x00\x01", 4)}) {
    EXPECT_EQ(cast::detail::base64UrlDecode(cast::detail::base64UrlEncode(bytes)), bytes);
  }
  EXPECT_EQ(cast::detail::base64UrlEncode("\xfb\xff"), "-_8");
  EXPECT_EQ(cast::detail::base64UrlDecode("a+b"), std::nullopt);  // base64, not base64url
}

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

// An unreadable TLS file is reported before anything is dialled, naming the file.
TEST(ClientTls, AnUnreadableFileIsNamed) {
  cast::TransportOptions options;
  options.tls = cast::ClientTls{"/nonexistent/cast-ca.pem", "", "", ""};
  try {
    cast::connectGrpc("127.0.0.1:1", "token", {"c", "vision", false}, options);
    FAIL() << "no error";
  } catch (const cast::InvalidArgumentError& e) {
    EXPECT_NE(e.message().find("cannot read a TLS file (CAST_TLS_CA/CERT/KEY): /nonexistent/cast-ca.pem"),
              std::string::npos)
        << e.message();
  }
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
  // Replaces the file later, once its modification time can differ from the
  // last write's: a reader that checks the time must see the change.
  void rewrite(const std::string& text) {
    std::this_thread::sleep_for(10ms);
    write(text);
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
  rewrite("second-and-longer\n");
  EXPECT_EQ(tokens.token(), "second-and-longer");
  EXPECT_FALSE(tokens.refresh()) << "nothing changed since";
  rewrite("third\n");
  EXPECT_TRUE(tokens.refresh());
  EXPECT_EQ(tokens.token(), "third");
}

TEST_F(TokenFile, TheFileIsCheckedAtMostEveryInterval) {
  write("first\n");
  cast::TokenSource tokens("first", path_, 60000ms);
  rewrite("second\n");
  EXPECT_EQ(tokens.token(), "first") << "checked again before the interval passed";
  EXPECT_TRUE(tokens.refresh()) << "refresh() reads it at once";
  EXPECT_EQ(tokens.token(), "second");
}

TEST_F(TokenFile, AnEmptyOrMissingFileKeepsTheLastToken) {
  write("good\n");
  cast::TokenSource tokens("initial", path_, 0ms);
  rewrite("");
  EXPECT_EQ(tokens.token(), "good");
  std::remove(path_.c_str());
  EXPECT_EQ(tokens.token(), "good");
  EXPECT_FALSE(tokens.refresh());
}

}  // namespace
