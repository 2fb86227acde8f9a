"""Values as the page shows them: through the writer's schema, nested Any values too, and what cannot be rendered."""

from __future__ import annotations

from google.protobuf import any_pb2, wrappers_pb2

from cast.auth import TokenSigner
from cast.client.credentials import TokenSource
from cast.core.records import Identity
from cast.v1 import task_manager_pb2 as tm_pb2
from cast.web.source import SystemSource
from cast.web.values import ValueDecoder
from tests.web.conftest import WebRun


def test_values_render_through_their_schemas_and_say_why_when_they_cannot(web_run: WebRun) -> None:
    secret = (web_run.run.runtime_dir / "secret").read_bytes().strip()
    endpoint = web_run.run.state()["endpoint"]
    source = SystemSource(endpoint, TokenSource(TokenSigner(secret).issue(Identity("cast-web", "", False))))
    try:
        decoder = ValueDecoder(source)
        data = any_pb2.Any()
        data.Pack(wrappers_pb2.StringValue(value="inside"))
        task = tm_pb2.Task(task_id="task-9", name="plan", component="planner", data=data,
                           state=tm_pb2.TASK_STATE_ADOPTED)
        shown = decoder.to_json("motor", "cast.v1.Task", task.SerializeToString())
        assert shown["state"] == "TASK_STATE_ADOPTED" and shown["name"] == "plan"
        assert shown["data"] == {"@type": "type.googleapis.com/google.protobuf.StringValue", "value": "inside"}
        unknown = decoder.to_json("motor", "acme.Unregistered", b"\x08\x01")
        assert unknown == {"@type": "acme.Unregistered", "@bytes": "CAE=",
                           "@error": "no schema registered for this type"}
        broken = decoder.to_json("motor", "cast.v1.Task", b"\xff\xff")
        assert broken["@error"].startswith("value does not parse as cast.v1.Task")
    finally:
        source.close()
