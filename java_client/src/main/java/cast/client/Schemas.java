package cast.client;

import com.google.protobuf.DescriptorProtos.FileDescriptorSet;
import com.google.protobuf.Descriptors.Descriptor;
import com.google.protobuf.Descriptors.FileDescriptor;
import java.util.ArrayDeque;
import java.util.Deque;
import java.util.LinkedHashMap;
import java.util.Map;

/** The schemas a client registers for the entry types it writes (docs/client-protocol.md). */
public final class Schemas {
  private Schemas() {}

  /**
   * The .proto file defining {@code type} and every file it imports, transitively
   * (google/protobuf/*.proto included): the server needs them all to build the type.
   */
  public static FileDescriptorSet filesOf(Descriptor type) {
    Map<String, FileDescriptor> seen = new LinkedHashMap<>();
    Deque<FileDescriptor> todo = new ArrayDeque<>();
    todo.push(type.getFile());
    while (!todo.isEmpty()) {
      FileDescriptor fd = todo.pop();
      if (seen.putIfAbsent(fd.getName(), fd) != null) {
        continue;
      }
      for (FileDescriptor dep : fd.getDependencies()) {
        todo.push(dep);
      }
    }
    FileDescriptorSet.Builder set = FileDescriptorSet.newBuilder();
    for (FileDescriptor fd : seen.values()) {
      set.addFile(fd.toProto());
    }
    return set.build();
  }
}
