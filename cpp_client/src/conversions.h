// Wire messages <-> the library's types (docs/client-protocol.md gives the
// messages): the only place that knows both, so the transport's calls and
// streams never build or read a message field by field themselves.
#pragma once

#include <google/protobuf/any.pb.h>
#include <google/protobuf/timestamp.pb.h>

#include <chrono>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "cast/filters.h"
#include "transport.h"
#include "cast/types.h"
#include "cast/v1/task_manager.pb.h"
#include "cast/v1/working_memory.pb.h"

namespace cast::detail {

// An entry's address on the wire.
v1::EntryAddress addressPb(const std::string& sa, const std::string& id);

// Fills an Any with serialised bytes of `type` (a full protobuf name): the
// library never parses values on the way out, it only labels them.
void setAny(google::protobuf::Any* any, const std::string& type, const std::string& data);

// The type name of an Any's type URL (what follows the last '/').
std::string typeFromUrl(const std::string& url);

// A timestamp as nanoseconds since the epoch.
std::int64_t nanos(const google::protobuf::Timestamp& t);

class ReadCall;

// An entry as the component model holds it (value bytes kept serialised). A
// value the server lent by shared memory (shared_value) is claimed on the
// read `call` it came on (shm_session.h): the record then holds its lease.
// UnavailableError when it cannot be (no call, or its bytes did not arrive).
EntryRecord entryFromPb(const v1::Entry& e, ReadCall* call = nullptr);

// A change event; its entry only if the server sent one (include_entry);
// `call` as for entryFromPb.
EventRecord eventFromPb(const v1::ChangeEvent& e, ReadCall* call = nullptr);

// A task; data type and bytes only if the task carries data.
TaskRecord taskFromPb(const v1::Task& t);

// A filter as the Watch call's create request carries it.
void filterToPb(const ChangeFilter& f, v1::ChangeFilter* pb);

// The revision and version a write got.
WriteResult writeResult(const v1::WriteResponse& r);

// The requests of the Write stream (WriteRequest with its id still unset),
// each carrying what the unary call of the same name takes.
v1::WriteRequest addRequest(const std::string& sa, const std::string& id, const std::string& type,
                            const std::string& data);
v1::WriteRequest overwriteRequest(const std::string& sa, const std::string& id, const std::string& type,
                                  const std::string& data, std::optional<std::uint64_t> expectedVersion);
v1::WriteRequest deleteRequest(const std::string& sa, const std::string& id,
                               std::optional<std::uint64_t> expectedVersion);
v1::WriteRequest batchRequest(const std::vector<BatchOp>& ops);
// A lock waiting up to `timeout` (nullopt: forever) unless `noWait`.
v1::WriteRequest lockRequest(const std::string& sa, const std::string& id, LockMode mode, bool noWait,
                             std::optional<std::chrono::milliseconds> timeout);
v1::WriteRequest unlockRequest(const std::string& sa, const std::string& id);

}  // namespace cast::detail
