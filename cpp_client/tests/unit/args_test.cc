// CAST_ARGS: a JSON object read through protobuf's JSON support.
#include <gtest/gtest.h>

#include "cast/args.h"
#include "cast/errors.h"

namespace {

TEST(Args, ReadsEveryJsonType) {
  auto args = cast::Args::fromJson(
      R"({"rate_hz": 20, "name": "s\u00e9g", "on": true, "scale": 0.5, "tags": ["a", "b"], "nothing": null})");
  EXPECT_EQ(args.getInt("rate_hz"), 20);
  EXPECT_DOUBLE_EQ(args.getDouble("scale"), 0.5);
  EXPECT_EQ(args.getString("name"), "s\xc3\xa9g");
  EXPECT_TRUE(args.getBool("on"));
  EXPECT_EQ(args.getStringList("tags"), (std::vector<std::string>{"a", "b"}));
  EXPECT_TRUE(args.has("rate_hz"));
  EXPECT_FALSE(args.has("nothing"));  // null counts as absent
  EXPECT_EQ(args.getString("nothing", "dflt"), "dflt");
  EXPECT_EQ(args.keys(), (std::vector<std::string>{"name", "nothing", "on", "rate_hz", "scale", "tags"}));
}

TEST(Args, MissingKeysGiveTheFallback) {
  auto args = cast::Args::fromJson("{}");
  EXPECT_EQ(args.getInt("n", 7), 7);
  EXPECT_EQ(args.getString("s", "x"), "x");
  EXPECT_FALSE(args.getBool("b"));
  EXPECT_TRUE(args.getStringList("l").empty());
}

TEST(Args, EmptyTextIsTheEmptyObject) {
  EXPECT_TRUE(cast::Args::fromJson("").keys().empty());
  EXPECT_TRUE(cast::Args::fromJson("  \n").keys().empty());
}

TEST(Args, AWrongTypeNamesTheKey) {
  auto args = cast::Args::fromJson(R"({"rate_hz": "fast", "n": 1.5})");
  try {
    args.getInt("rate_hz");
    FAIL() << "no error";
  } catch (const cast::InvalidArgumentError& e) {
    EXPECT_EQ(e.message(), "argument 'rate_hz' must be an integer, got a string");
  }
  EXPECT_THROW(args.getInt("n"), cast::InvalidArgumentError);
  EXPECT_THROW(args.getBool("n"), cast::InvalidArgumentError);
  EXPECT_THROW(args.getStringList("n"), cast::InvalidArgumentError);
}

TEST(Args, NotAnObjectOrNotJsonIsRefused) {
  EXPECT_THROW(cast::Args::fromJson("[1, 2]"), cast::InvalidArgumentError);
  EXPECT_THROW(cast::Args::fromJson("42"), cast::InvalidArgumentError);
  try {
    cast::Args::fromJson("{rate_hz: 20");
    FAIL() << "no error";
  } catch (const cast::InvalidArgumentError& e) {
    EXPECT_NE(e.message().find("CAST_ARGS is not valid JSON"), std::string::npos) << e.message();
  }
}

TEST(Args, RoundTripsToJson) {
  auto args = cast::Args::fromJson(R"({"a": 1, "b": {"c": [true]}})");
  auto again = cast::Args::fromJson(args.toJson());
  EXPECT_EQ(again.getInt("a"), 1);
  EXPECT_TRUE(again.values().fields().at("b").struct_value().fields().at("c").list_value().values(0).bool_value());
}

}  // namespace
