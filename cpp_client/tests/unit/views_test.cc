// A value read without copying (cast/views.h): ValueView over a record, the
// bytes of one field, and a change's view sharing its event. Shared memory
// itself is tests/unit/shm_test.cc and tests/server/shared_memory_test.cc.
#include <gtest/gtest.h>

#include <sstream>

#include "cast/views.h"
#include "cast_testing.pb.h"
#include "unit_types.pb.h"

namespace {

using cast::ByteSpan;
using cast::ValueView;
using cast::testing::Counter;
using cast::testing::Pose;

std::shared_ptr<const cast::detail::EntryRecord> record(const google::protobuf::Message& value) {
  auto r = std::make_shared<cast::detail::EntryRecord>();
  r->address = {"p", "vision"};
  r->type = value.GetDescriptor()->full_name();
  r->data = value.SerializeAsString();
  r->version = 4;
  r->author = "w";
  r->revision = 9;
  r->modifiedNs = 12345;
  return r;
}

std::string text(ByteSpan bytes) { return std::string(bytes.chars()); }

TEST(ValueView, GivesTheSerialisedValueAndTheEntrysMetadataWithoutCopying) {
  Pose pose;
  pose.set_x(1.5);
  pose.set_label("door");
  pose.add_tags("a");
  auto r = record(pose);
  ValueView view(r);
  EXPECT_EQ(view.id(), "p");
  EXPECT_EQ(view.address().subarchitecture, "vision");
  EXPECT_EQ(view.type(), "cast.testing.Pose");
  EXPECT_EQ(view.version(), 4u);
  EXPECT_EQ(view.author(), "w");
  EXPECT_EQ(view.revision(), 9u);
  EXPECT_EQ(view.modifiedNs(), 12345);
  EXPECT_FALSE(view.shared());
  EXPECT_EQ(view.data().data(), reinterpret_cast<const std::byte*>(r->data.data()));  // the record's bytes, not a copy
  EXPECT_EQ(text(view.data()), pose.SerializeAsString());
  EXPECT_EQ(text(view.field(3)), "door");
  EXPECT_EQ(text(view.field(4)), "a");
  EXPECT_TRUE(view.field(9).empty());  // absent
  EXPECT_EQ(view.decode<Pose>().label(), "door");
  EXPECT_THROW(view.decode<Counter>(), cast::InvalidArgumentError);
  std::ostringstream shown;
  shown << view;
  EXPECT_EQ(shown.str(), "ValueView(vision/p type=cast.testing.Pose v=4 " + std::to_string(r->data.size()) +
                             " bytes in bytes)");
}

TEST(ValueView, AFieldIsTheLastOccurrenceAndANumberIsNotBytes) {
  Pose first;
  first.set_label("old");
  Pose second;
  second.set_label("new");
  second.set_x(2);
  auto r = record(first);
  std::const_pointer_cast<cast::detail::EntryRecord>(r)->data += second.SerializeAsString();  // merged, as protobuf would
  ValueView view(r);
  EXPECT_EQ(text(view.field(3)), "new");
  try {
    view.field(1);
    FAIL() << "a double field was read as bytes";
  } catch (const cast::InvalidArgumentError& e) {
    EXPECT_EQ(e.message(), "entry 'p' in subarchitecture 'vision': field 1 is a number, not bytes, a string or a message");
  }
  auto broken = std::make_shared<cast::detail::EntryRecord>(*r);
  broken->data = std::string("\x1a\x10short", 7);  // field 3 claims 16 bytes, has 5
  EXPECT_THROW(ValueView(broken).field(3), cast::InvalidArgumentError);
  broken->data = std::string("\x1a\xff", 2);  // a varint that never ends
  EXPECT_THROW(ValueView(broken).field(3), cast::InvalidArgumentError);
}

TEST(ValueView, AReleasedOrMovedFromViewSaysSo) {
  auto r = record(Counter());
  ValueView view(r);
  ValueView moved = std::move(view);
  EXPECT_EQ(moved.version(), 4u);
  try {
    view.data();  // NOLINT(bugprone-use-after-move): what a moved-from view does is the point
    FAIL() << "a moved-from view was read";
  } catch (const cast::InvalidArgumentError& e) {
    EXPECT_EQ(e.message(), "this view was released: read the entry again");
  }
  EXPECT_EQ(r.use_count(), 2);
  moved.release();
  EXPECT_EQ(r.use_count(), 1);  // the value is given back with the last holder
  EXPECT_THROW(moved.field(1), cast::InvalidArgumentError);
  moved.release();  // idempotent
}

TEST(ValueView, AChangesViewSharesItsEventAndNeedsAnEntry) {
  cast::detail::EventRecord event;
  event.operation = cast::Operation::Overwrite;
  event.address = {"p", "vision"};
  Counter c;
  c.set_writer("w");
  c.set_value(3);
  event.entry = *record(c);
  cast::WorkingMemoryChange change(std::move(event));
  ValueView view = change.view();
  EXPECT_EQ(view.decode<Counter>().value(), 3);
  EXPECT_EQ(text(view.field(1)), "w");
  cast::WorkingMemoryChange bare(cast::detail::EventRecord{});
  EXPECT_THROW(bare.view(), cast::InvalidArgumentError);
}

TEST(ByteSpan, IsASpanOfConstBytes) {
  const std::string s = "abcdef";
  ByteSpan span(reinterpret_cast<const std::byte*>(s.data()), s.size());
  EXPECT_EQ(span.size(), 6u);
  EXPECT_EQ(static_cast<char>(span[2]), 'c');
  EXPECT_EQ(text(span.subspan(2, 3)), "cde");
  EXPECT_EQ(text(span.subspan(4)), "ef");
  EXPECT_EQ(text(span.subspan(4, 100)), "ef");
  EXPECT_THROW(span.subspan(7), std::out_of_range);
  std::size_t n = 0;
  for (std::byte b : span) n += static_cast<std::size_t>(b) > 0 ? 1 : 0;
  EXPECT_EQ(n, 6u);
  EXPECT_TRUE(ByteSpan().empty());
}

}  // namespace
