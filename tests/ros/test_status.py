"""What the bridge shows: its mappings with rates and errors in `cast components` and the web view, ROS -> WM
latency in `cast stats`; a value that does not fit its ROS type is refused, named, counted, and the bridge goes on."""

from __future__ import annotations

import json
import os
import subprocess
import time
from pathlib import Path
from typing import Any

from cast.auth import TokenSigner
from cast.client.credentials import TokenSource
from cast.core.records import Identity
from cast.web.model import LiveModel
from cast.web.source import SystemSource
from tests.conftest import SECRET, VENV_BIN, ServerHandle, stop_process, wait_for
from tests.ros.bridge_support import start_bridge
from tests.ros.ros_env import helper, ros2_python
from tests.ros.test_ros2_bridge import published, status_of

SETTINGS: dict[str, Any] = {
    "version": 2, "status_period": 0.3,
    "to_wm": [{"topic": "/camera/image_raw", "type": "sensor_msgs/msg/Image", "subarchitecture": "vision",
               "id": "camera", "max_rate": 10}],
    "to_ros": [{"watch": {"subarchitecture": "vision", "id": "display"}, "topic": "/display",
                "type": "sensor_msgs/msg/Image"}],
}


def cli(server: ServerHandle, *args: str) -> str:
    env = {**os.environ, "CAST_TOKEN": server.token("cast-cli", ""), "CAST_ENDPOINT": server.endpoint}
    done = subprocess.run([str(VENV_BIN / "cast"), *args, "--endpoint", server.endpoint], env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout


def web_page_mappings(server: ServerHandle, tmp_path: Path) -> dict[str, dict[str, str]]:
    """What the architecture view shows of the bridge's mappings: `cast web` and Debian's chromium, signed in."""
    from playwright.sync_api import sync_playwright

    from tests.web.conftest import CHROMIUM, LINK

    env = {**os.environ, "CAST_TOKEN": server.token("cast-cli", ""), "CAST_SECRET": SECRET}
    web = subprocess.Popen([str(VENV_BIN / "cast"), "web", "--endpoint", server.endpoint, "--listen", "127.0.0.1:0"],
                           env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=tmp_path)
    try:
        assert web.stdout is not None
        lines: list[str] = []
        link = None
        while link is None:
            line = web.stdout.readline()
            assert line, "cast web ended:\n" + "".join(lines)
            lines.append(line)
            found = LINK.search(line)
            link = found.group(1) if found else None
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=str(CHROMIUM))
            page = browser.new_page()
            page.set_default_timeout(30_000)
            page.goto(link)
            page.goto(link.split("/login")[0] + "/#architecture")
            rows = page.locator('[data-component="bridge"] .mapping')
            rows.nth(1).wait_for()
            shown = {row.get_attribute("data-mapping") or "": {"text": row.inner_text(),
                                                             "class": row.get_attribute("class") or "",
                                                             "title": row.get_attribute("title") or ""}
                     for row in rows.all()}
            browser.close()
        return shown
    finally:
        stop_process(web, 10)


def test_components_stats_and_the_web_view_show_the_mappings_rates_errors_and_latency(
        ros_server: ServerHandle, ros2: dict[str, str], ros2_types: Path, tmp_path: Path) -> None:
    from ros2.sensor_msgs.msg.image_pb2 import Image

    bridge = start_bridge(ros_server, "bridge", "motor", SETTINGS, ros2, tmp_path / "bridge.log")
    watcher = ros_server.connect("watcher", "vision")
    publisher = None
    try:
        wait_for(lambda: status_of(watcher, "bridge"), 60, "the bridge's first status")
        # An entry ROS cannot hold (is_bigendian is a uint8): refused, named, counted; the next one goes through.
        watcher.add("display", Image(is_bigendian=300, encoding="mono8"))
        wait_for(lambda: status_of(watcher, "bridge").mappings[1].errors == 1, 30, "the refusal to be counted")
        watcher.overwrite("display", Image(is_bigendian=1, encoding="mono8", height=1, width=1, step=1, data=b"x"))
        publisher = helper(ros2_python(), "ros2_node.py", "publish", "/camera/image_raw", "image", "30", "30",
                           env=ros2, log=tmp_path / "images.log")
        assert publisher.wait(60) == 0, (tmp_path / "images.log").read_text()
        def counted() -> Any:
            s = status_of(watcher, "bridge")
            images, display = s.mappings[0], s.mappings[1]
            # Asserted, so that a timeout says which count stopped short.
            assert (images.received, images.pending, display.delivered) == (30, 0, 1), (
                f"images received {images.received} of 30, pending {images.pending}; display delivered "
                f"{display.delivered} of 1")
            return s

        status = wait_for(counted, 30, "every image counted")
        # max_rate: at most 10 a second written (from the first stamp to the last, one more for the start).
        stamps = sorted(published(tmp_path / "images.log").values())
        limited = status.mappings[0]
        assert limited.dropped > 0 and limited.delivered + limited.dropped == 30
        assert limited.delivered <= 10 * (stamps[-1] - stamps[0]) / 1e9 + 2
        refused = status.mappings[1]
        assert refused.last_error == ("topic /display: entry display of 'vision': field is_bigendian: 300 does not "
                                      "fit a ROS uint8 (0 to 255)")
        assert refused.last_error_time.seconds > 0

        rows = json.loads(cli(ros_server, "components", "--json"))
        (mine,) = [r for r in rows if r["id"] == "bridge"]
        image_row, display_row = mine["mappings"]
        assert (image_row["direction"], image_row["topic"], image_row["ros_type"], image_row["subarchitecture"],
                image_row["entry"]) == ("to_wm", "/camera/image_raw", "sensor_msgs/msg/Image", "vision",
                                        "latest camera")
        assert image_row["received"] == 30 and image_row["delivered"] + image_row["dropped"] == 30
        assert (display_row["errors"], display_row["delivered"]) == (1, 1)
        assert "field is_bigendian: 300" in display_row["last_error"]
        table = cli(ros_server, "components")
        assert "2 bridge mappings" in table and "/camera/image_raw" in table and "latest camera" in table, table

        stats = json.loads(cli(ros_server, "stats", "--json"))
        (latency,) = [r for r in stats["bridges"] if r["direction"] == "to_wm"]
        assert latency["latency_count"] == latency["delivered"] > 0
        assert 0 < latency["latency_p50_s"] <= latency["latency_p99_s"] <= latency["latency_max_s"] < 10
        assert "ROS -> WM latency" in cli(ros_server, "stats")

        # The web view's state: the bridge's component carries its mappings with their rates and errors.
        tokens = TokenSource(TokenSigner(SECRET.encode()).issue(Identity("cast-web", "", False)))
        model = LiveModel(SystemSource(ros_server.endpoint, tokens))
        try:
            model.refresh()
            state = json.loads(model.state()[1])
        finally:
            model.close()
        (component,) = [c for c in state["components"] if c["id"] == "bridge"]
        assert [m["topic"] for m in component["mappings"]] == ["/camera/image_raw", "/display"]
        assert component["mappings"][1]["errors"] == 1 and component["mappings"][0]["delivered"] > 0
        assert time.time() - component["mappings"][0]["status_time"] < 60

        # ... and the page draws them under the bridge's component, in a real browser.
        shown = web_page_mappings(ros_server, tmp_path)
        assert shown["/camera/image_raw"]["text"].startswith("ROS → WM /camera/image_raw → vision: ")
        assert "WM → ROS /display → vision" in shown["/display"]["text"] and "1 errors" in shown["/display"]["text"]
        assert "bad" in shown["/display"]["class"] and "field is_bigendian: 300" in shown["/display"]["title"]
    finally:
        if publisher is not None:
            stop_process(publisher, 5)
        stop_process(bridge, 10)
        watcher._cast_close()
