"""The bridge in the system YAML: `cast check` reports mistakes in its mappings on their lines; the launch."""

from __future__ import annotations

import json
import subprocess
import textwrap
from pathlib import Path

from cast.config import read_config
from cast.orchestrator.launchers import launcher_for
from tests.conftest import VENV_BIN
from tests.orchestrator.test_config import one, problems

WRONG = """\
    subarchitectures:
      vision:
        components:
          cam:
            language: ros
            ros:
              version: 2
              to_wm:
                - topic: /camera/image_raw
                  type: sensor_msgs/Image
                  store: latest
                  keep: 4
                  qos: {reliabilty: best_effort, depth: 0}
                - {topic: "bad topic", type: sensor_msgs/msg/Image, subarchitecture: motor, stor: each}
                - {topic: /x, type: std_msgs/msg/String, subarchitecture: visoin}
                - {topic: /y, type: std_msgs/msg/String, id: camera/image_raw}
              to_ros:
                - watch: {subarchitecture: motor, type: ros2.geometry_msgs.msg.Twis, id: a, author: b}
                  topic: /cmd_vel
                  type: geometry_msgs/msg/Twist
                - {watch: {subarchitecture: motor}, topic: /odd}
          empty: {language: ros, kind: managed}
      motor: {}
    """


def test_mistakes_in_mappings_are_reported_on_their_lines_with_suggestions(tmp_path: Path) -> None:
    found = problems(tmp_path, WRONG)
    one(found, 10, "to_wm[0].type", "'sensor_msgs/Image' is not a ROS 2 message type: write package/msg/Name "
                                    "(sensor_msgs/msg/Image?)")
    one(found, 12, "to_wm[0].keep", "'store: latest' overwrites one entry: remove keep")
    one(found, 13, "qos.reliabilty", "unknown key 'reliabilty' (did you mean 'reliability'?)")
    one(found, 13, "qos.depth", "must be a positive whole number, not 0")
    one(found, 14, "stor", "unknown key 'stor' (did you mean 'store'?)")
    one(found, 14, "to_wm[1].topic", "'bad topic' is not a ROS topic name")
    one(found, 14, "to_wm[1].subarchitecture", "make it 'privileged: true' to write into 'motor'")
    one(found, 15, "to_wm[2].subarchitecture", "unknown subarchitecture 'visoin' (did you mean 'vision'?)")
    one(found, 16, "to_wm[3]", "writes the same entries as to_wm[0] (latest 'camera/image_raw' in 'vision')")
    one(found, 18, "to_ros[0].watch.type", "entry type 'ros2.geometry_msgs.msg.Twist', not "
                                           "'ros2.geometry_msgs.msg.Twis'")
    one(found, 18, "to_ros[0].watch.author", "watch one entry (id) or one author's entries, not both")
    one(found, 21, "to_ros.type", "missing: write 'type:'")
    one(found, 22, "empty.ros", "a ROS bridge (language: ros) needs a 'ros:' section")
    one(found, 22, "empty.kind", "the ROS bridge is unmanaged")
    assert len([p for p in found if not p.warning]) == 14, "\n".join(map(str, found))


def test_cast_check_prints_them_as_file_line_error_key_message(tmp_path: Path) -> None:
    path = tmp_path / "system.yaml"
    path.write_text(textwrap.dedent(WRONG))
    out = subprocess.run([str(VENV_BIN / "cast"), "check", str(path)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 1
    assert (f"{path}:10: error: subarchitectures.vision.components.cam.ros.to_wm[0].type: 'sensor_msgs/Image' is "
            "not a ROS 2 message type: write package/msg/Name (sensor_msgs/msg/Image?) (this bridge speaks ROS 2)"
            in out.stdout + out.stderr)


def test_a_bridge_is_launched_with_its_interpreter_and_its_mappings(tmp_path: Path) -> None:
    path = tmp_path / "system.yaml"
    path.write_text(textwrap.dedent("""\
        subarchitectures:
          vision:
            components:
              cam:
                language: ros
                ros:
                  version: 1
                  to_wm: [{topic: /cam/image_raw, type: sensor_msgs/Image}]
              cam2:
                language: ros
                ros:
                  python: ./py/bin/python
                  to_ros: [{watch: {subarchitecture: vision}, topic: /answers, type: std_msgs/msg/String}]
        """))
    (tmp_path / "py" / "bin").mkdir(parents=True)
    (tmp_path / "py" / "bin" / "python").write_text("#!/bin/sh\n")
    (tmp_path / "py" / "bin" / "python").chmod(0o755)
    config, found = read_config(path, environ={})
    assert config is not None and not found.errors, [str(p) for p in found.items]
    cam, cam2 = config.components
    launcher = launcher_for("ros")
    env = {"CAST_ROS1_PYTHON": "/usr/bin/python3"}
    assert launcher.command(cam, config, env) == ["/usr/bin/python3", "-m", "cast.run",
                                                  "cast.bridges.ros.ros1:Ros1Bridge"]
    assert launcher.command(cam2, config, env) == [str(tmp_path / "py" / "bin" / "python"), "-m", "cast.run",
                                                   "cast.bridges.ros.ros2:Ros2Bridge"]
    settings = json.loads(launcher.environment(cam, config, env)["CAST_ROS_BRIDGE"])
    assert settings["version"] == 1 and settings["to_wm"][0]["topic"] == "/cam/image_raw"
    assert settings["to_wm"][0]["qos"] == {"reliability": "reliable", "durability": "volatile",
                                           "history": "keep_last", "depth": 10}
