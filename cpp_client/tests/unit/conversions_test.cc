// Wire messages <-> library types (src/conversions.h): every field lands
// where the component model reads it, and the enums keep the proto's numbers.
#include <gtest/gtest.h>

#include "conversions.h"

namespace {

using namespace cast;

google::protobuf::Timestamp at(std::int64_t seconds, std::int32_t nanos) {
  google::protobuf::Timestamp t;
  t.set_seconds(seconds);
  t.set_nanos(nanos);
  return t;
}

v1::Entry entryPb() {
  v1::Entry e;
  *e.mutable_address() = detail::addressPb("vision", "roi:1");
  e.set_type("demo.Roi");
  detail::setAny(e.mutable_value(), "demo.Roi", std::string("\x08\x01", 2));
  e.set_version(7);
  e.set_author("segmenter");
  *e.mutable_modified() = at(1700000000, 5);
  e.set_revision(42);
  return e;
}

TEST(Conversions, AnyCarriesTheTypeUrlAndTheBytesUnparsed) {
  google::protobuf::Any any;
  detail::setAny(&any, "demo.Roi", std::string("\xff\x00", 2));
  EXPECT_EQ(any.type_url(), "type.googleapis.com/demo.Roi");
  EXPECT_EQ(any.value(), std::string("\xff\x00", 2));
  EXPECT_EQ(detail::typeFromUrl(any.type_url()), "demo.Roi");
  EXPECT_EQ(detail::typeFromUrl("demo.Roi"), "demo.Roi");  // no prefix: the name itself
}

TEST(Conversions, AnEntryKeepsEveryField) {
  const detail::EntryRecord r = detail::entryFromPb(entryPb());
  EXPECT_EQ(r.address.id, "roi:1");
  EXPECT_EQ(r.address.subarchitecture, "vision");
  EXPECT_EQ(r.type, "demo.Roi");
  EXPECT_EQ(r.data, std::string("\x08\x01", 2));
  EXPECT_EQ(r.version, 7u);
  EXPECT_EQ(r.author, "segmenter");
  EXPECT_EQ(r.revision, 42u);
  EXPECT_EQ(r.modifiedNs, 1700000000LL * 1000000000LL + 5);
}

TEST(Conversions, AnEventCarriesItsEntryOnlyWhenSent) {
  v1::ChangeEvent e;
  e.set_revision(42);
  e.set_operation(v1::OPERATION_OVERWRITE);
  *e.mutable_address() = detail::addressPb("vision", "roi:1");
  e.set_type("demo.Roi");
  e.set_source_component("segmenter");
  e.set_source_subarchitecture("vision");
  e.set_version(7);
  *e.mutable_time() = at(2, 3);
  detail::EventRecord r = detail::eventFromPb(e);
  EXPECT_EQ(r.revision, 42u);
  EXPECT_EQ(r.operation, Operation::Overwrite);
  EXPECT_EQ(r.address.id, "roi:1");
  EXPECT_EQ(r.sourceComponent, "segmenter");
  EXPECT_EQ(r.sourceSubarchitecture, "vision");
  EXPECT_EQ(r.version, 7u);
  EXPECT_EQ(r.timeNs, 2000000003);
  EXPECT_FALSE(r.entry.has_value());
  EXPECT_EQ(r.skipped, 0u);
  EXPECT_EQ(WorkingMemoryChange(r).skipped(), 0u);

  // What a Latest watch's server skipped travels with the change.
  e.set_skipped(3);
  e.set_first_skipped_revision(38);
  const WorkingMemoryChange conflated(detail::eventFromPb(e));
  EXPECT_EQ(conflated.skipped(), 3u);
  EXPECT_EQ(conflated.firstSkippedRevision(), 38u);
  e.clear_skipped();
  e.clear_first_skipped_revision();

  *e.mutable_entry() = entryPb();
  e.set_operation(v1::OPERATION_DELETE);
  r = detail::eventFromPb(e);
  EXPECT_EQ(r.operation, Operation::Delete);
  ASSERT_TRUE(r.entry.has_value());
  EXPECT_EQ(r.entry->author, "segmenter");
}

TEST(Conversions, ATaskKeepsItsDecisionAndData) {
  v1::Task t;
  t.set_task_id("t-1");
  t.set_name("segment");
  t.set_subarchitecture("vision");
  t.set_component("segmenter");
  t.set_priority(-3);
  t.set_state(v1::TASK_STATE_COMPLETED);
  t.set_outcome(v1::TASK_OUTCOME_ABANDONED);
  t.set_reason("gave up");
  detail::TaskRecord r = detail::taskFromPb(t);
  EXPECT_EQ(r.taskId, "t-1");
  EXPECT_EQ(r.name, "segment");
  EXPECT_EQ(r.subarchitecture, "vision");
  EXPECT_EQ(r.component, "segmenter");
  EXPECT_EQ(r.priority, -3);
  EXPECT_EQ(r.state, TaskState::Completed);
  EXPECT_EQ(r.outcome, TaskOutcome::Abandoned);
  EXPECT_EQ(r.reason, "gave up");
  EXPECT_EQ(r.dataType, "");  // no data: no type either

  detail::setAny(t.mutable_data(), "demo.Roi", "bytes");
  r = detail::taskFromPb(t);
  EXPECT_EQ(r.dataType, "demo.Roi");
  EXPECT_EQ(r.data, "bytes");
}

TEST(Conversions, AFilterIsSentAsGiven) {
  ChangeFilter f;
  f.operations = {Operation::Add, Operation::Delete};
  f.type = "demo.Roi";
  f.id = "roi:1";
  f.subarchitecture = "vision";
  f.sourceComponent = "segmenter";
  f.sourceSubarchitecture = "language";
  f.includeEntry = true;
  v1::ChangeFilter pb;
  detail::filterToPb(f, &pb);
  ASSERT_EQ(pb.operations_size(), 2);
  EXPECT_EQ(pb.operations(0), v1::OPERATION_ADD);
  EXPECT_EQ(pb.operations(1), v1::OPERATION_DELETE);
  EXPECT_EQ(pb.type(), "demo.Roi");
  EXPECT_EQ(pb.id(), "roi:1");
  EXPECT_EQ(pb.subarchitecture(), "vision");
  EXPECT_EQ(pb.source_component(), "segmenter");
  EXPECT_EQ(pb.source_subarchitecture(), "language");
  EXPECT_TRUE(pb.include_entry());
}

TEST(Conversions, AWriteGivesItsRevisionAndVersion) {
  v1::WriteResponse w;
  w.set_revision(9);
  w.set_version(1795460940838790ULL);
  const WriteResult r = detail::writeResult(w);
  EXPECT_EQ(r.revision, 9u);
  EXPECT_EQ(r.version, 1795460940838790ULL);
}

// The Write stream's requests carry what the unary calls took.
TEST(Conversions, WriteRequestsCarryTheUnaryCallsRequests) {
  v1::WriteRequest add = detail::addRequest("vision", "roi:1", "demo.Roi", "\x08\x01");
  ASSERT_TRUE(add.has_add());
  EXPECT_EQ(add.add().address().id(), "roi:1");
  EXPECT_EQ(add.add().value().type_url(), "type.googleapis.com/demo.Roi");
  EXPECT_EQ(add.id(), 0u);  // the stream numbers it when it is sent

  v1::WriteRequest overwrite = detail::overwriteRequest("vision", "roi:1", "demo.Roi", "", 7);
  EXPECT_TRUE(overwrite.overwrite().has_expected_version());
  EXPECT_EQ(overwrite.overwrite().expected_version(), 7u);
  EXPECT_FALSE(detail::overwriteRequest("vision", "roi:1", "demo.Roi", "", std::nullopt)
                   .overwrite()
                   .has_expected_version());
  EXPECT_EQ(detail::deleteRequest("vision", "roi:1", 0).delete_().expected_version(), 0u);
  EXPECT_TRUE(detail::deleteRequest("vision", "roi:1", 0).delete_().has_expected_version());

  std::vector<detail::BatchOp> ops(3);
  ops[0] = {Operation::Add, "vision", "a", "demo.Roi", "x", std::nullopt};
  ops[1] = {Operation::Overwrite, "vision", "b", "demo.Roi", "y", 4};
  ops[2] = {Operation::Delete, "vision", "c", "", "", std::nullopt};
  v1::WriteRequest batch = detail::batchRequest(ops);
  ASSERT_EQ(batch.batch().operations_size(), 3);
  EXPECT_EQ(batch.batch().operations(0).add().address().id(), "a");
  EXPECT_EQ(batch.batch().operations(1).overwrite().expected_version(), 4u);
  EXPECT_EQ(batch.batch().operations(2).delete_().address().id(), "c");

  EXPECT_EQ(detail::unlockRequest("vision", "roi:1").unlock().address().id(), "roi:1");
}

// timeout_ms 0 means "no bound" on the wire, so a lock's own timeout is sent
// as at least 1 ms, and a lock that does not wait sends none.
TEST(Conversions, ALockSendsItsTimeoutInMilliseconds) {
  using std::chrono::milliseconds;
  v1::WriteRequest lock = detail::lockRequest("vision", "roi:1", LockMode::ODR, false, milliseconds(2500));
  EXPECT_EQ(lock.lock().mode(), v1::LOCK_MODE_ODR);
  EXPECT_FALSE(lock.lock().no_wait());
  EXPECT_EQ(lock.timeout_ms(), 2500u);
  EXPECT_EQ(detail::lockRequest("vision", "roi:1", LockMode::O, false, std::nullopt).timeout_ms(), 0u);
  EXPECT_EQ(detail::lockRequest("vision", "roi:1", LockMode::O, false, milliseconds(0)).timeout_ms(), 1u);
  v1::WriteRequest tryLock = detail::lockRequest("vision", "roi:1", LockMode::O, true, milliseconds(2500));
  EXPECT_TRUE(tryLock.lock().no_wait());
  EXPECT_EQ(tryLock.timeout_ms(), 0u);
}

}  // namespace
