// The filter helpers build the filters docs/client-protocol.md describes.
#include <gtest/gtest.h>

#include <sstream>

#include "cast/filters.h"
#include "cast_testing.pb.h"

namespace {

using cast::ChangeFilter;
using cast::Operation;

TEST(Filters, LocalTypeFilterUsesTheFullNameAndTheOwnSa) {
  ChangeFilter f = cast::localTypeFilter<cast::testing::Counter>();
  EXPECT_EQ(f.type, "cast.testing.Counter");
  EXPECT_TRUE(f.local);
  EXPECT_TRUE(f.subarchitecture.empty());
  EXPECT_TRUE(f.operations.empty());
  EXPECT_FALSE(f.includeEntry);
  ChangeFilter resolved = f.resolve("vision");
  EXPECT_EQ(resolved.subarchitecture, "vision");
  EXPECT_FALSE(resolved.local);
  EXPECT_EQ(resolved.type, "cast.testing.Counter");
}

TEST(Filters, GlobalTypeFilterMatchesEverySa) {
  ChangeFilter f = cast::globalTypeFilter<cast::testing::Pose>({Operation::Add, Operation::Delete}, true);
  EXPECT_EQ(f.type, "cast.testing.Pose");
  EXPECT_FALSE(f.local);
  EXPECT_EQ(f.resolve("vision").subarchitecture, "");
  EXPECT_EQ(f.operations, (std::set<Operation>{Operation::Add, Operation::Delete}));
  EXPECT_TRUE(f.includeEntry);
}

TEST(Filters, TypeFiltersByName) {
  EXPECT_EQ(cast::localTypeFilter("x.Y"), cast::localTypeFilter("x.Y"));
  EXPECT_EQ(cast::globalTypeFilter("x.Y").type, "x.Y");
  EXPECT_NE(cast::localTypeFilter("x.Y"), cast::globalTypeFilter("x.Y"));
}

TEST(Filters, AddressFilterDefaultsToTheOwnSa) {
  ChangeFilter own = cast::addressFilter("e1");
  EXPECT_EQ(own.id, "e1");
  EXPECT_TRUE(own.local);
  EXPECT_EQ(own.resolve("motor").subarchitecture, "motor");

  ChangeFilter other = cast::addressFilter("e1", {Operation::Overwrite}, "language");
  EXPECT_FALSE(other.local);
  EXPECT_EQ(other.resolve("motor").subarchitecture, "language");
  EXPECT_EQ(other.operations, std::set<Operation>{Operation::Overwrite});

  EXPECT_EQ(cast::addressFilter(cast::WorkingMemoryAddress{"e1", "language"}, {Operation::Overwrite}), other);
}

TEST(Filters, SourceFilterMatchesEverySaUnlessGiven) {
  ChangeFilter f = cast::sourceFilter("segmenter");
  EXPECT_EQ(f.sourceComponent, "segmenter");
  EXPECT_EQ(f.resolve("vision").subarchitecture, "");
  EXPECT_EQ(cast::sourceFilter("segmenter", {}, "vision").resolve("motor").subarchitecture, "vision");
}

TEST(Filters, OperationFilterLocalOrGlobal) {
  ChangeFilter global = cast::operationFilter({Operation::Delete});
  EXPECT_EQ(global.operations, std::set<Operation>{Operation::Delete});
  EXPECT_EQ(global.resolve("vision").subarchitecture, "");
  ChangeFilter local = cast::operationFilter({Operation::Add}, true);
  EXPECT_EQ(local.resolve("vision").subarchitecture, "vision");
}

TEST(Filters, DuplicateOperationsCollapse) {
  EXPECT_EQ(cast::operationFilter({Operation::Add, Operation::Add}).operations.size(), 1u);
}

TEST(Filters, WithEntryCopies) {
  ChangeFilter f = cast::localTypeFilter<cast::testing::Counter>();
  ChangeFilter g = f.withEntry();
  EXPECT_FALSE(f.includeEntry);
  EXPECT_TRUE(g.includeEntry);
  EXPECT_EQ(g.type, f.type);
}

TEST(Filters, PrintsReadably) {
  std::ostringstream os;
  os << cast::addressFilter("e1", {Operation::Add}).withEntry();
  EXPECT_EQ(os.str(), "ChangeFilter{operations=ADD id=e1 subarchitecture=<own> include_entry}");
}

}  // namespace
