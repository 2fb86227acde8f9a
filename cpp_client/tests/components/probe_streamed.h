// cast_probe's commands for the streamed write path, in a file of
// their own: pipelined writes, large values, and the watch options (delivery,
// priority, a slow callback). tests/interop/test_streamed_interop.py drives them.
#pragma once

#include <google/protobuf/struct.pb.h>

#include <chrono>
#include <cstdint>
#include <string>

#include "cast/cast.h"
#include "probe_json.h"

namespace cast::probe {

// `n` addAsync calls (ids PREFIX-0 .. PREFIX-<n-1>, Counters of value i), all
// sent before any future is waited for. Returns {"revisions": [...] in call
// order (0 for a refused one), "errors": [{"index", "error", "code"}]}.
std::string addAsync(Component& component, const std::string& prefix, int n);

// `n` overwriteAsync calls of one entry (Counters of value 1 .. n), then waits
// for them all: {"revisions", "versions", "errors"} as addAsync.
std::string overwriteAsync(Component& component, const std::string& id, int n);

// Adds a google.protobuf.BytesValue of `size` bytes, byte i = i % 251:
// {"revision", "version", "size", "crc32"}.
std::string bigWrite(Component& component, const std::string& id, const std::string& sa, std::size_t size);

// Reads a google.protobuf.BytesValue: {"size", "crc32", "version", "author"}.
std::string bigRead(Component& component, const std::string& id, const std::string& sa);

// The options of a watch spec ({"delivery": "queue|latest", "priority":
// "high|medium|low"}); the defaults when absent.
WatchOptions watchOptions(const google::protobuf::Struct& spec);

// How long a watch spec's callback sleeps ({"slow_ms": N}; 0 when absent).
std::chrono::milliseconds slowCallback(const google::protobuf::Struct& spec);

// Adds what a change says of latest delivery ("skipped",
// "first_skipped_revision") and, for a BytesValue it carries, its "size" and
// "crc32" (not the bytes: they may be megabytes).
void describeStreamed(Object& event, const WorkingMemoryChange& change);

// The CRC-32 (zlib's, as Python's zlib.crc32 and Java's CRC32) of `data`.
std::uint32_t crc32(const std::string& data);

}  // namespace cast::probe
