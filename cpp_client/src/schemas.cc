#include "cast/schemas.h"

#include <set>
#include <string>

namespace cast {

namespace {
void visit(const google::protobuf::FileDescriptor* file, std::set<std::string>& seen,
           google::protobuf::FileDescriptorSet& out) {
  if (!seen.insert(file->name()).second) return;
  for (int i = 0; i < file->dependency_count(); ++i) visit(file->dependency(i), seen, out);
  // CopyTo leaves out json_name and source info, exactly as the Python
  // client's CopyToProto does: the server refuses a file registered twice
  // with different content, so every language must send the same bytes.
  file->CopyTo(out.add_file());
}
}  // namespace

google::protobuf::FileDescriptorSet schemaFilesOf(const google::protobuf::Descriptor* type) {
  google::protobuf::FileDescriptorSet out;
  std::set<std::string> seen;
  visit(type->file(), seen, out);
  return out;
}

}  // namespace cast
