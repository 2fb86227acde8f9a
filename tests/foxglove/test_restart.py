"""The live view across a server restart: the viewer stays connected, the view resumes by itself, and changes it could
not get are a marked gap (a /cast/gaps message and a warning in the app), never silent."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cast_testing_pb2 import Counter

from cast.errors import AlreadyExistsError, UnavailableError
from tests.foxglove.conftest import FoxgloveClient, ViewProcess, start_view
from tests.foxglove.test_cast_foxglove import CHANGES, GAPS, subscribed
from tests.reliability.conftest import kill9, serve, write_config


def _add(component: Any, entry_id: str, value: int) -> None:
    """Add, retrying while the server is away (ALREADY_EXISTS: an earlier try was applied)."""
    while True:
        try:
            component.add(entry_id, Counter(value=value))
            return
        except UnavailableError:
            time.sleep(0.05)
        except AlreadyExistsError:
            return


def test_a_server_restarted_without_its_history_is_a_gap_and_the_view_goes_on(
    tmp_path: Path, views: list[ViewProcess], clients: Callable[[str], FoxgloveClient]
) -> None:
    config = write_config(tmp_path / "system.yaml", {"system": "memory", "subarchitectures": {"vision": {}}})
    server = serve(config)
    port = server.endpoint.rpartition(":")[2]
    writer = server.connect("w", "vision")
    try:
        view = start_view(server.endpoint)
        views.append(view)
        client = clients(view.url)
        client.subscribe(GAPS, CHANGES)
        subscribed(client, lambda i: _add(writer, f"old-{i}", i))
        kill9(server)
        server = serve(config, listen=f"127.0.0.1:{port}")  # memory only: a new history, revisions from 1 again
        (gap,) = client.wait(lambda: client.decode(GAPS), "the gap marker")
        assert gap["subarchitecture"] == "vision" and "restarted without it" in gap["reason"]
        warning = client.wait(lambda: [s for s in client.status if "gap in subarchitecture 'vision'" in s["message"]],
                              "the warning in the app")
        assert warning[0]["level"] == 1  # warning
        _add(writer, "new", 7)
        client.wait(lambda: any(c.address.id == "new" for c in client.decode(CHANGES)), "a change after the restart")
        assert view.process.poll() is None
        assert view.stop(signal.SIGINT) == 0, view.output()
        assert "gap in subarchitecture 'vision'" in view.output()
    finally:
        writer._cast_close()
        server.stop()
