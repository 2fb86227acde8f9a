"""`make demo-ros`: the scene demo on a real ROS 1 camera driver, its answers printed by rostopic echo (docs/ros.md,
"The demo")."""

from __future__ import annotations

import sys
from pathlib import Path

from tests.conftest import ROOT, run_to_end
from tests.ros.ros_env import ros1_python


def test_the_demo_sees_the_table_through_image_publisher_and_answers_on_a_ros_topic(tmp_path: Path) -> None:
    ros1_python()  # the bridge's interpreter (fails, never skips, without it)
    assert (ROOT / "build" / "python-examples" / "ros1" / ".generated").is_file(), \
        "the demo's ROS entry types are missing: `make ros-demo-types` (make test-python runs it)"
    done = run_to_end([sys.executable, str(ROOT / "examples" / "ros" / "run_demo.py"), "--for", "12", "--set",
                       "COLOUR_LANGUAGE=python", "--no-status", "--runtime-dir", str(tmp_path / "rt")],
                      "make demo-ros", 120, cwd=ROOT)
    assert done.returncode == 0, done.stdout + done.stderr
    echoed = [line.removeprefix("[rostopic echo /cast/answers] ") for line in done.stdout.splitlines()
              if line.startswith("[rostopic echo /cast/answers] ")]
    # What the segmenter found in the picture's pixels, as the answers say, printed by rostopic.
    assert 'data: "q3 what colour is the cone? -> green"' in echoed, done.stdout
    assert 'data: "q4 how many cubes are there? -> three cubes"' in echoed, done.stdout
    assert 'data: "q1 what is left of the red cube? -> the blue ball is just left of the red cube"' in echoed
    assert "new region region-1 at x=-0.45, y=0.30" in done.stdout
