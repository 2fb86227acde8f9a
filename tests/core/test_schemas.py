"""Schemas compared by meaning, the server's own files preloaded: no client can poison a type for others.

The sequences come from a Node.js client (protobufjs ships google/protobuf/*.proto
without their options) that registered first and made every later Python write
of a StringValue fail.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from cast_testing_pb2 import Pose
from google.protobuf import descriptor_pb2, wrappers_pb2

from cast.core.journal import Journal
from cast.core.records import Identity
from cast.core.schemas import WELL_KNOWN, SchemaRegistry, files_of
from cast.core.system import System
from cast.errors import InvalidArgumentError, LockedError, SchemaConflictError

W = Identity("w", "vision")
FileProto = descriptor_pb2.FileDescriptorProto


def stripped(files: list[FileProto]) -> list[FileProto]:
    """What protobufjs sends: no options, no json_name, no source info."""
    out = []
    for f in files:
        copy = FileProto()
        copy.CopyFrom(f)
        copy.ClearField("options")
        copy.ClearField("source_code_info")
        for m in copy.message_type:
            m.ClearField("options")
            for field in m.field:
                field.ClearField("json_name")
                field.ClearField("options")
        out.append(copy)
    return out


def user_file() -> FileProto:
    return next(f for f in files_of(Pose.DESCRIPTOR) if f.name == "cast_testing.proto")


def test_well_known_files_are_preloaded_and_client_copies_are_ignored() -> None:
    reg = SchemaRegistry()
    names = {fd.name for fd in WELL_KNOWN}
    assert {"google/protobuf/wrappers.proto", "google/protobuf/any.proto", "google/protobuf/timestamp.proto",
            "google/protobuf/struct.proto", "google/protobuf/descriptor.proto"} <= names
    assert all(reg.is_own(name) and reg.known_file(name) for name in names)
    # An option-less copy first (as protobufjs sends it), then a real write of a StringValue.
    bare = stripped(files_of(wrappers_pb2.StringValue.DESCRIPTOR))
    bare[0].message_type[0].field[0].name = "renamed"  # even a copy that really differs is not looked at
    assert "google.protobuf.StringValue" in reg.register(bare)
    reg.validate("google.protobuf.StringValue", wrappers_pb2.StringValue(value="hi").SerializeToString())
    served = reg.files_for("google.protobuf.StringValue")[-1]
    assert served.message_type[0].field[0].name == "value" and served.options.java_package == "com.google.protobuf"
    with pytest.raises(InvalidArgumentError, match="does not parse as google.protobuf.StringValue"):
        reg.validate("google.protobuf.StringValue", b"\xff\xff\xff\xff")


def test_a_user_file_without_options_first_then_protocs_copy_is_the_same_schema() -> None:
    reg = SchemaRegistry()
    reg.register(stripped([user_file()]))
    reg.register([user_file()])  # protoc's copy, with options and json names: the same types
    reg.register(stripped([user_file()]))
    assert reg.files_for("cast.testing.Pose")[-1].message_type[0].field[0].json_name == ""  # the first is kept


@pytest.mark.parametrize(
    ("change", "named"),
    [
        (lambda f: setattr(f.message_type[1].field[2], "name", "title"), "field 3 is 'optional string label = 3'"),
        (lambda f: setattr(f.message_type[1].field[0], "type", FileProto().message_type.add().field.add().TYPE_FLOAT),
         "cast.testing.Pose: field 1"),
        (lambda f: f.message_type[1].field.add(name="z", number=9, type=1, label=1), "field 9"),
        (lambda f: setattr(f, "package", "other"), "package is 'cast.testing'"),
        (lambda f: f.message_type.add(name="Extra"), "message cast.testing.Extra"),
    ],
)
def test_a_registration_that_really_differs_is_refused_naming_the_difference_and_changes_nothing(
    change: object, named: str
) -> None:
    reg = SchemaRegistry()
    reg.register([user_file()])
    before = reg.types()
    changed = user_file()
    change(changed)  # type: ignore[operator]
    with pytest.raises(SchemaConflictError, match="already registered with other types") as err:
        reg.register([changed])
    assert named in err.value.message
    assert isinstance(err.value, LockedError) and err.value.code == "FAILED_PRECONDITION"
    assert reg.types() == before


def test_a_registration_is_all_or_nothing() -> None:
    reg = SchemaRegistry()
    good = FileProto(name="good.proto", package="g")
    good.message_type.add(name="Fine").field.add(name="a", number=1, type=9, label=1)
    bad = FileProto(name="bad.proto", package="b", dependency=["good.proto"])
    bad.message_type.add(name="Broken").field.add(name="x", number=1, type=11, label=1, type_name=".g.Nowhere")
    with pytest.raises(InvalidArgumentError, match="invalid"):
        reg.register([good, bad])
    assert not reg.known("g.Fine") and not reg.known_file("good.proto")
    with pytest.raises(InvalidArgumentError, match="imports 'missing.proto'"):
        reg.register([FileProto(name="lonely.proto", dependency=["missing.proto"])])


def test_after_a_durable_restart_the_same_rules_hold_and_stored_copies_of_own_files_are_dropped(
    tmp_path: Path,
) -> None:
    path = tmp_path / "wm.db"
    s = System("t", ["vision"], journal=Journal(path, "batch"))
    s.schemas.register(stripped([user_file()]))
    s.close()
    # An older server stored its clients' copies of well-known files: one, option-less and altered, is there.
    poison = stripped(files_of(wrappers_pb2.StringValue.DESCRIPTOR))[0]
    poison.message_type[0].field[0].name = "renamed"
    journal = Journal(path, "batch")
    journal.append_schemas([(poison.name, poison.SerializeToString())])
    journal.close()

    s2 = System("t", ["vision"], journal=Journal(path, "batch"))
    s2.host.add(W, "vision", "s", "google.protobuf.StringValue",
                wrappers_pb2.StringValue(value="hi").SerializeToString())
    assert s2.schemas.files_for("google.protobuf.StringValue")[-1].message_type[0].field[0].name == "value"
    s2.schemas.register([user_file()])  # protoc's copy of the option-less stored file: the same schema
    changed = user_file()
    changed.message_type[1].field[2].name = "title"
    with pytest.raises(SchemaConflictError):
        s2.schemas.register([changed])
    s2.close()
    s3 = System("t", ["vision"], journal=Journal(path, "batch"))
    assert s3.journal is not None
    stored = [FileProto.FromString(d).name for d in s3.journal.load().schemas]
    assert "google/protobuf/wrappers.proto" not in stored and "cast_testing.proto" in stored
    s3.close()


def test_a_file_that_defines_a_type_another_file_defines_is_refused_not_an_internal_error() -> None:
    # What proto-loader makes up: one file per package, 'google_protobuf.proto', with the wrappers in it.
    reg = SchemaRegistry()
    made_up = FileProto(name="google_protobuf.proto", package="google.protobuf")
    made_up.message_type.add(name="DoubleValue").field.add(name="value", number=1, type=1, label=1)
    with pytest.raises(InvalidArgumentError, match="defines google.protobuf.DoubleValue, which "
                                                   "'google/protobuf/wrappers.proto' already defines"):
        reg.register([made_up])
    assert not reg.known_file("google_protobuf.proto")
