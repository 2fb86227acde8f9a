// Tokens are JWTs (HS256): reading their claims, and minting one from the
// system's secret, byte for byte as cast.auth.TokenSigner (PyJWT) does.
#include <gtest/gtest.h>

#include "cast/errors.h"
#include "cast/token.h"

namespace {

const std::string kSecret = "test-secret-0123456789abcdef-0123456789";  // tests/conftest.py SECRET

// Made with PyJWT: jwt.encode({"c": "planner", "s": "coordination", "p": True,
// "iat": 1700000000, "exp": 1700003600}, kSecret, algorithm="HS256").
const std::string kPlannerToken =
    "eyJhbGciOiJIUzI1NiIsInR5cCI6IkpXVCJ9."
    "eyJjIjoicGxhbm5lciIsInMiOiJjb29yZGluYXRpb24iLCJwIjp0cnVlLCJpYXQiOjE3MDAwMDAwMDAsImV4cCI6MTcwMDAwMzYwMH0."
    "mON1cpsY000YjhzfewPiFgGFw69BHVWWsbe6zfS8uGs";

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

}  // namespace
