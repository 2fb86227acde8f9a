// Entry schemas: the .proto file descriptors a client registers with the
// servers before the first write of each type, so that `cast get` and
// `cast watch` render entries as JSON and the server rejects bytes that do
// not parse as the declared type.
#pragma once

#include <google/protobuf/descriptor.h>
#include <google/protobuf/descriptor.pb.h>

namespace cast {

// The file defining `type` and every file it imports, transitively
// (google/protobuf/*.proto included), dependencies first.
google::protobuf::FileDescriptorSet schemaFilesOf(const google::protobuf::Descriptor* type);

}  // namespace cast
