"""`make demo-ros`: the scene demo with its camera frames from a real ROS 1 driver (docs/ros.md, "The demo").

Starts a roscore on 127.0.0.1 (a free port), Debian's C++ ``image_publisher``
publishing a picture of the demo's table on /cam/image_raw at 10 Hz, and
``rostopic echo /cast/answers``; then ``cast run configs/demo.yaml --set
SEGMENTER_LANGUAGE=ros`` (configs/demo/segmenter-ros.yaml): the ROS bridge
writes the frames into the vision WM, the segmenter finds the objects in the
pixels, the recognisers and the answerer do as in ``make demo``, and the
answers come back out on /cast/answers, printed by rostopic. Everything it
started is stopped at the end.

    python examples/ros/run_demo.py [cast run options, e.g. --for 20 --set COLOUR_LANGUAGE=python]
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time
import xmlrpc.client
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
WORK = ROOT / "build" / "ros-demo"
IMAGE_PUBLISHER = Path("/usr/lib/image_publisher/image_publisher")
IMAGE_PUBLISHER_PREFIX = ROOT / "build" / "ros1" / "image_publisher" / "usr"


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (for the roscore of this run)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def echo_lines(proc: subprocess.Popen[str], prefix: str) -> None:
    """Print each line ``proc`` writes, after ``prefix`` (rostopic's separators left out)."""
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.strip() and line.strip() != "---":
            # One write per line, its newline included: print() writes the text and the newline apart when
            # stdout is unbuffered, and `cast run`'s lines, on the same pipe, could then land in between.
            sys.stdout.write(f"{prefix} {line.rstrip()}\n")
            sys.stdout.flush()


def main() -> int:
    """Start roscore, image_publisher and rostopic echo, then `cast run` the demo; its exit status."""
    sys.path[:0] = [str(ROOT / "examples" / "python"), str(ROOT / "build" / "python-examples")]
    from cast_examples.camera import write_table_picture

    WORK.mkdir(parents=True, exist_ok=True)
    picture = WORK / "table.png"
    write_table_picture(picture)
    port = free_port()
    env = dict(os.environ, ROS_MASTER_URI=f"http://127.0.0.1:{port}", ROS_IP="127.0.0.1",
               ROS_HOME=str(WORK / "ros-home"), ROS_PACKAGE_PATH=str(IMAGE_PUBLISHER_PREFIX / "share"),
               CMAKE_PREFIX_PATH=str(IMAGE_PUBLISHER_PREFIX), PYTHONUNBUFFERED="1")
    started: list[subprocess.Popen[str]] = []

    def start(command: list[str], **kwargs: object) -> subprocess.Popen[str]:
        proc = subprocess.Popen(command, env=env, text=True, start_new_session=True, **kwargs)  # type: ignore[call-overload]
        started.append(proc)
        return proc

    try:
        start(["roscore", "-p", str(port)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        master, deadline = xmlrpc.client.ServerProxy(env["ROS_MASTER_URI"]), time.monotonic() + 30
        while True:
            try:
                master.getSystemState("/demo")
                break
            except OSError:
                if time.monotonic() > deadline:
                    print("roscore did not start", file=sys.stderr)
                    return 1
                time.sleep(0.1)
        print(f"roscore on 127.0.0.1:{port}; image_publisher publishes {picture} on /cam/image_raw", flush=True)
        start([str(IMAGE_PUBLISHER), "__name:=cam", str(picture), "_publish_rate:=10", "_frame_id:=camera"],
              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        echo = start(["rostopic", "echo", "/cast/answers"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        threading.Thread(target=echo_lines, args=(echo, "[rostopic echo /cast/answers]"), daemon=True).start()
        run = subprocess.run([str(Path(sys.executable).parent / "cast"), "run", str(ROOT / "configs" / "demo.yaml"),
                              "--set", "SEGMENTER_LANGUAGE=ros", *sys.argv[1:]], env=env)
        time.sleep(0.5)  # the last answer's echo
        return run.returncode
    finally:
        for proc in reversed(started):
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    os.killpg(proc.pid, signal.SIGKILL)


if __name__ == "__main__":
    sys.exit(main())
