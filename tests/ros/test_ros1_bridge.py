"""The ROS 1 bridge against Debian's ROS 1: roscore on 127.0.0.1, the C++ image_publisher driver, rostopic.

image_publisher publishes a picture the test made; the bridge writes the
frames into a WM, where a C++ component (built on `cast ros-types` output)
checks the pixels; in reverse, `rostopic echo -n 1` prints a message a
component wrote.
"""

from __future__ import annotations

import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import pytest

from tests.conftest import ServerHandle, stop_process, wait_for
from tests.ros.bridge_support import start_bridge
from tests.ros.builds import printed, wait_ready
from tests.ros.ros_env import IMAGE_PUBLISHER_PREFIX, RosCore, helper, ros1_python, roscore
from tests.ros.test_ros2_bridge import fnv1a, status_of

IMAGE_PUBLISHER = Path("/usr/lib/image_publisher/image_publisher")
WIDTH, HEIGHT = 64, 48


def picture(path: Path) -> bytes:
    """Write a PNG (RGB) whose every pixel differs; the BGR bytes image_publisher will publish."""
    pixels = [((x * 4) % 256, (y * 5) % 256, (x * y) % 256) for y in range(HEIGHT) for x in range(WIDTH)]
    rows = b"".join(b"\x00" + b"".join(bytes(p) for p in pixels[y * WIDTH:(y + 1) * WIDTH]) for y in range(HEIGHT))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", WIDTH, HEIGHT, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))
    return b"".join(bytes((b, g, r)) for r, g, b in pixels)


def image_publisher(core: RosCore, png: Path, log: Path, name: str = "cam") -> subprocess.Popen[str]:
    """Debian's C++ image_publisher node publishing ``png`` at 10 Hz on /<name>/image_raw."""
    if not IMAGE_PUBLISHER.is_file() or not (IMAGE_PUBLISHER_PREFIX / "share" / "image_publisher").is_dir():
        pytest.fail("image_publisher is not installed with its nodelet description: `make ros-deps` does it")
    return subprocess.Popen([str(IMAGE_PUBLISHER), f"__name:={name}", str(png), "_publish_rate:=10",
                             "_frame_id:=camera_optical"], env=core.env(), stdout=log.open("w"),
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


SETTINGS = {
    "version": 1,
    "node": "cast_bridge",
    "status_period": 0.5,
    "to_wm": [{"topic": "/cam/image_raw", "type": "sensor_msgs/Image", "subarchitecture": "vision", "id": "camera"}],
    "to_ros": [{"watch": {"subarchitecture": "language", "id": "answer"}, "topic": "/cast/answer",
                "type": "std_msgs/String"}],
}


# The first test of the run to use it builds the C++ component (a few minutes on a busy machine).
@pytest.mark.timeout(600)
def test_image_publisher_frames_reach_a_cpp_component_and_rostopic_echo_prints_an_entry(
        ros_server: ServerHandle, ros_cpp_build: Path, ros1_types: Path, tmp_path: Path) -> None:
    from ros1.sensor_msgs.msg.image_pb2 import Image
    from ros1.std_msgs.msg.string_pb2 import String

    cpp_exe = ros_cpp_build
    expected = picture(tmp_path / "table.png")
    with roscore(tmp_path / "ros-home") as core:
        bridge = start_bridge(ros_server, "bridge", "language", SETTINGS, core.env(), tmp_path / "bridge.log")
        cpp = subprocess.Popen([str(cpp_exe)], env=ros_server.env("cpp_watcher", "vision", args={
            "watch": {"ros1.sensor_msgs.msg.Image": {"sa": "vision", "count": 3}}}), stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT, text=True)
        procs: list[subprocess.Popen[str]] = [cpp]
        watcher = ros_server.connect("watcher", "language")
        try:
            wait_ready(cpp)
            wait_for(lambda: status_of_sa(watcher, "language"), 60, "the bridge's first status entry")
            procs.append(image_publisher(core, tmp_path / "table.png", tmp_path / "camera.log"))
            out, _ = cpp.communicate(timeout=60)
            assert cpp.returncode == 0, out
            frames = printed(out)
            seqs = []
            for got in frames:
                seqs.append(got.pop("seq"))
                assert got.pop("stamp_ns") > 0
                assert got == {"type": "ros1.sensor_msgs.msg.Image", "id": "camera", "frame_id": "camera_optical",
                               "height": HEIGHT, "width": WIDTH, "encoding": "bgr8", "is_bigendian": 0,
                               "step": WIDTH * 3, "size": WIDTH * HEIGHT * 3, "fnv": fnv1a(expected)}
            assert seqs == sorted(seqs) and len(set(seqs)) == 3  # three frames in order, as the driver numbered them
            assert watcher.get("camera", Image, subarchitecture="vision").data == expected

            # In reverse: an entry a component writes is what `rostopic echo -n 1` prints.
            echo = subprocess.Popen(["rostopic", "echo", "-n", "1", "/cast/answer"], env=core.env(),
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            procs.append(echo)
            answer = String(data="two cubes, one ball: ünïcødé too")
            watcher.add("answer", answer)
            deadline = time.monotonic() + 60
            while echo.poll() is None and time.monotonic() < deadline:
                time.sleep(0.3)  # until rostopic has connected to the bridge's publisher
                watcher.overwrite("answer", answer)
            out, _ = echo.communicate(timeout=10)
            assert echo.returncode == 0, out
            # rostopic prints what is not ASCII as escapes of the characters (ü is U+00FC)
            assert out.splitlines()[0] == r'data: "two cubes, one ball: \xFCn\xEFc\xF8d\xE9 too"', out
        finally:
            for p in procs:
                stop_process(p, 5)
            stop_process(bridge, 10)
            watcher._cast_close()


def status_of_sa(watcher: object, sa: str) -> object:
    import cast
    from cast.v1 import bridge_pb2

    assert isinstance(watcher, cast.Component)
    try:
        return watcher.get("bridge.status", bridge_pb2.BridgeStatus, subarchitecture=sa)
    except cast.NotFoundError:
        return None


__all__ = ["picture", "image_publisher", "status_of"]


READING_MSG = """\
# A reading of a team's own sensor: a message package of the test's own, built with genpy.
uint8 LEVEL_LOW=0
uint8 LEVEL_HIGH=2
Header header
uint8 level
float64 value
int16[3] triple
string label
geometry_msgs/Point[] points
time taken
duration window
"""


def own_message_package(root: Path) -> Path:
    """cast_test_msgs with the message Reading, generated by genpy as a team's build would: its Python path."""
    src = root / "src" / "cast_test_msgs" / "msg"
    src.mkdir(parents=True)
    (src / "Reading.msg").write_text(READING_MSG)
    out = root / "python" / "cast_test_msgs"
    genpy = ["/usr/bin/python3", "/usr/lib/genpy/genmsg_py.py", "-p", "cast_test_msgs", "-o", str(out / "msg")]
    includes = [f"-Icast_test_msgs:{src}", "-Istd_msgs:/usr/share/std_msgs/msg",
                "-Igeometry_msgs:/usr/share/geometry_msgs/msg"]
    for command in ([*genpy, *includes, str(src / "Reading.msg")], [*genpy, "--initpy"]):
        done = subprocess.run(command, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, f"genpy (make ros-deps installs it): {done.stdout}{done.stderr}"
    (out / "__init__.py").write_text("")
    return root / "python"


def test_a_teams_own_message_package_is_bridged_as_soon_as_it_is_on_the_ros_path(
        ros_server: ServerHandle, ros1_types: Path, tmp_path: Path) -> None:
    python_path = own_message_package(tmp_path / "workspace")
    with roscore(tmp_path / "ros-home") as core:
        env = {**core.env(), "PYTHONPATH": str(python_path)}
        # The team's types for its own components: cast ros-types on the same path.
        done = subprocess.run([str(ros1_python()), "-m", "cast.cli", "ros-types", "--ros", "1", "-q",
                               "cast_test_msgs/Reading", "-o", str(tmp_path / "protos")], env=env,
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        (tmp_path / "py").mkdir()
        protos = sorted(p.relative_to(tmp_path / "protos").as_posix() for p in (tmp_path / "protos").rglob("*.proto"))
        subprocess.run([sys.executable, "-m", "grpc_tools.protoc", f"-I{tmp_path / 'protos'}",
                        f"--python_out={tmp_path / 'py'}", *protos], check=True)
        sys.path.insert(0, str(tmp_path / "py"))
        from ros1.cast_test_msgs.msg.reading_pb2 import Reading

        settings = {"version": 1, "status_period": 0.3, "to_wm": [
            {"topic": "/tank/reading", "type": "cast_test_msgs/Reading", "subarchitecture": "language",
             "id": "tank"}]}
        bridge = start_bridge(ros_server, "bridge", "language", settings, core.env(), tmp_path / "bridge.log",
                              overlay={"PYTHONPATH": str(python_path)})
        publisher = helper(ros1_python(), "ros1_node.py", "reading", "/tank/reading", env=env,
                           log=tmp_path / "reading.log")
        watcher = ros_server.connect("watcher", "language")
        try:
            reading = wait_for(lambda: watcher.exists("tank") and watcher.get("tank", Reading), 60,
                               "the team's message in the WM")
            assert reading.header.frame_id == "tank" and reading.header.seq >= 0
            assert (reading.header.stamp.secs, reading.header.stamp.nsecs) == (1700000000, 123456789)
            assert (reading.level, reading.value, list(reading.triple)) == (2, -0.125, [-32768, 0, 32767])
            assert reading.label == "tank 3: ünïcødé"
            assert [(p.x, p.y, p.z) for p in reading.points] == [(1.0, 2.0, 3.0), (-1.0, float("inf"), 0.0)]
            assert (reading.taken.secs, reading.taken.nsecs) == (1700000001, 5)
            assert (reading.window.secs, reading.window.nsecs) == (-2, 500)
        finally:
            stop_process(publisher, 5)
            stop_process(bridge, 10)
            watcher._cast_close()
