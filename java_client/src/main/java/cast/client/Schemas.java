package cast.client;

import com.google.protobuf.Any;
import com.google.protobuf.DescriptorProtos.FileDescriptorSet;
import com.google.protobuf.Descriptors.Descriptor;
import com.google.protobuf.Descriptors.FileDescriptor;
import com.google.protobuf.Message;
import java.util.ArrayDeque;
import java.util.Deque;
import java.util.LinkedHashMap;
import java.util.Map;
import java.util.Set;
import java.util.concurrent.ConcurrentHashMap;

/** The schemas a client registers for the entry types it writes (docs/client-protocol.md). */
final class Schemas {
  private Schemas() {}

  /**
   * The types one connection registered, by SA: each is registered with the server of an SA once,
   * before its first write there. Only the server that will hold the value is told, so a server
   * that hangs or is away cannot hold up writes to the others.
   */
  static final class Registered {
    private final Set<String> types = ConcurrentHashMap.newKeySet();
    private final Object lock = new Object();

    /**
     * {@code value} as a write into {@code sa} sends it, after registering its type with that SA's
     * server through {@code transport} if not yet done.
     */
    Any pack(Message value, String sa, Transport transport) {
      if (value == null) {
        throw new InvalidArgumentError("entry values are protobuf messages, got null");
      }
      String key = value.getDescriptorForType().getFullName() + "\u0000" + sa;
      if (!types.contains(key)) {
        synchronized (lock) {
          if (!types.contains(key)) {
            // Tools render the type as JSON, and the server checks the bytes, from now on.
            transport.registerSchemas(filesOf(value.getDescriptorForType()), sa);
            types.add(key);
          }
        }
      }
      return Types.pack(value);
    }
  }

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
