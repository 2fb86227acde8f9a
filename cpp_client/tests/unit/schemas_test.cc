// The schema files a client registers: a type's file and everything it
// imports, dependencies first, in the form every language sends.
#include <gtest/gtest.h>

#include "cast/schemas.h"
#include "cast_fidelity.pb.h"
#include "unit_types.pb.h"

namespace {

TEST(Schemas, AFileWithoutImportsIsSentAlone) {
  auto set = cast::schemaFilesOf(cast::testing::RichEntry::descriptor());
  ASSERT_EQ(set.file_size(), 1);
  const auto& f = set.file(0);
  EXPECT_EQ(f.name(), "cast_fidelity.proto");
  EXPECT_EQ(f.package(), "cast.testing");
  EXPECT_EQ(f.syntax(), "proto3");
  ASSERT_GE(f.message_type_size(), 1);
  EXPECT_EQ(f.message_type(0).name(), "RichEntry");
}

TEST(Schemas, ImportsComeFirstTransitively) {
  auto set = cast::schemaFilesOf(cast::unittest::Observation::descriptor());
  std::vector<std::string> names;
  for (const auto& f : set.file()) names.push_back(f.name());
  EXPECT_EQ(names, (std::vector<std::string>{"google/protobuf/timestamp.proto", "cast_testing.proto",
                                             "unit_types.proto"}));
}

TEST(Schemas, NestedTypesUseTheirFile) {
  auto set = cast::schemaFilesOf(cast::testing::RichEntry::Point::descriptor());
  ASSERT_EQ(set.file_size(), 1);
  EXPECT_EQ(set.file(0).name(), "cast_fidelity.proto");
}

TEST(Schemas, NoSourceInfoNorJsonNames) {
  // The server refuses a file registered twice with different bytes, so
  // what C++ sends must match what the Python client's CopyToProto sends.
  auto set = cast::schemaFilesOf(cast::testing::RichEntry::descriptor());
  EXPECT_FALSE(set.file(0).has_source_code_info());
  for (const auto& field : set.file(0).message_type(0).field()) {
    EXPECT_FALSE(field.has_json_name()) << field.name();
  }
}

}  // namespace
