package cast.client;

import static org.junit.jupiter.api.Assertions.*;

import cast.testing.CastTesting.Counter;
import cast.testing.CastTesting.Pose;
import cast.testing.RichEntry;
import com.google.protobuf.DescriptorProtos.FileDescriptorProto;
import java.util.List;
import java.util.stream.Collectors;
import org.junit.jupiter.api.Test;

class TypesTest {
  @Test
  void typeNamesAreFullProtobufNames() {
    assertEquals("cast.testing.Counter", Types.typeName(Counter.class));
    assertEquals("cast.testing.RichEntry", Types.typeName(RichEntry.class));
    assertEquals("cast.v1.Entry", Types.typeName(cast.v1.Entry.class));
  }

  @Test
  void decodingChecksTheType() {
    Counter c = Counter.newBuilder().setWriter("w").setValue(3).build();
    assertEquals(c, Types.decode(Counter.class, "cast.testing.Counter", c.toByteString(), "entry 'x'", "vision", ""));
    InvalidArgumentError e =
        assertThrows(
            InvalidArgumentError.class,
            () -> Types.decode(Pose.class, "cast.testing.Counter", c.toByteString(), "entry 'x'", "vision", ""));
    // Word for word Python's message.
    assertEquals(
        "entry 'x' in subarchitecture 'vision' has type cast.testing.Counter, not cast.testing.Pose: read it with the"
            + " right class",
        e.getMessage());
  }

  @Test
  void packUsesTheStandardTypeUrl() {
    var any = Types.pack(Counter.newBuilder().setValue(1).build());
    assertEquals("type.googleapis.com/cast.testing.Counter", any.getTypeUrl());
    assertEquals("cast.testing.Counter", Types.typeOf(any));
  }

  @Test
  void schemasHoldTheTypesFileAndEveryImportTransitively() {
    // cast/v1/working_memory.proto imports entry.proto and any.proto; entry.proto imports timestamp.proto.
    List<String> names =
        Schemas.filesOf(cast.v1.AddRequest.getDescriptor()).getFileList().stream()
            .map(FileDescriptorProto::getName)
            .collect(Collectors.toList());
    assertEquals(
        List.of(
            "cast/v1/working_memory.proto",
            "cast/v1/entry.proto",
            "google/protobuf/any.proto",
            "google/protobuf/timestamp.proto"),
        names.stream().sorted((a, b) -> order(a) - order(b)).collect(Collectors.toList()));
    assertEquals(names.size(), names.stream().distinct().count(), "each file once");
    List<String> rich =
        Schemas.filesOf(RichEntry.getDescriptor()).getFileList().stream()
            .map(FileDescriptorProto::getName)
            .collect(Collectors.toList());
    assertEquals(List.of("cast_fidelity.proto"), rich);
  }

  private static int order(String name) {
    return List.of(
            "cast/v1/working_memory.proto",
            "cast/v1/entry.proto",
            "google/protobuf/any.proto",
            "google/protobuf/timestamp.proto")
        .indexOf(name);
  }
}
