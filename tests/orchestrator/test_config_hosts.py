"""Configuration across hosts: hosts:, host: and advertise:, each mistake on its line (docs/multihost.md)."""

from __future__ import annotations

import os
import subprocess
import textwrap
from pathlib import Path

import yaml
from jsonschema import Draft7Validator

from cast.config import read_config
from cast.config.schema import system_schema
from tests.orchestrator.conftest import CAST, COMPONENTS
from tests.orchestrator.test_config import one, problems


def test_unknown_host_names_its_line_with_a_suggestion(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        hosts:
          arm: 10.0.0.2:7070
        servers:
          main: {listen: "10.0.0.1:7000", subarchitectures: [vision]}
        subarchitectures:
          vision:
            components:
              a: {class: "m:A", host: amr}
              b: {class: "m:B", host: arm}
        """)
    one(found, 8, "components.a.host", "unknown host 'amr' (did you mean 'arm'?)")
    assert len([p for p in found if not p.warning]) == 1, [str(p) for p in found]


def test_a_host_without_a_hosts_section_says_where_to_name_it(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        subarchitectures:
          vision:
            components:
              a: {class: "m:A", host: arm}
        """)
    one(found, 4, "components.a.host", "name the machines of the system and their agents' addresses under 'hosts:'")


def test_a_remote_component_needs_a_server_other_hosts_reach(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        hosts: {arm: {agent: "10.0.0.2:7070"}}
        servers:
          main: {listen: "127.0.0.1:0", subarchitectures: [vision]}
          other: {listen: "0.0.0.0:7001", subarchitectures: [motor]}
        subarchitectures:
          vision:
            components:
              a: {class: "m:A", host: arm}
          motor:
            components:
              b: {class: "m:B", host: arm}
              c: {class: "m:C"}
        """)
    one(found, 8, "components.a.host", "server 'main', listens on the loopback address 127.0.0.1:0")
    one(found, 11, "components.b.host", "server 'other', listens on the wildcard address 0.0.0.0:7001")
    assert len(found) == 3, [str(p) for p in found]  # b needs both the directory and its SA's server


def test_a_server_on_another_host_needs_every_server_reachable(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        hosts: {arm: {agent: "10.0.0.2:7070"}}
        servers:
          main: {listen: "127.0.0.1:0", subarchitectures: [vision]}
          far: {listen: "0.0.0.0:0", host: arm, subarchitectures: [motor]}
        subarchitectures:
          vision:
            components:
              a: {class: "m:A"}
          motor:
            components:
              b: {class: "m:B", in_process: true}
        """)
    # far dials the directory (its start barrier) and is dialled by it (routes): both must be reachable.
    one(found, 4, "servers.far.host", "but server 'main' listens on the loopback address 127.0.0.1:0")
    one(found, 4, "servers.far.host", "but it listens on the wildcard address 0.0.0.0:0")
    assert len(found) == 2, [str(p) for p in found]
    fixed = problems(tmp_path, """\
        hosts: {arm: {agent: "10.0.0.2:7070"}}
        servers:
          main: {listen: "0.0.0.0:0", advertise: "10.0.0.1:0", subarchitectures: [vision]}
          far: {listen: "10.0.0.2:0", host: arm, subarchitectures: [motor]}
        subarchitectures:
          vision: {components: {a: {class: "m:A"}}}
          motor: {components: {b: {class: "m:B", in_process: true}}}
        """)
    assert not fixed, [str(p) for p in fixed]


def test_advertise_makes_a_server_reachable_and_its_port_0_is_the_bound_port(tmp_path: Path) -> None:
    path = tmp_path / "system.yaml"
    path.write_text(textwrap.dedent("""\
        hosts: {arm: "10.0.0.2:7070"}
        servers:
          main: {listen: "0.0.0.0:0", advertise: "robot.local:0", subarchitectures: [vision]}
        subarchitectures:
          vision:
            components:
              a: {class: "m:A", host: arm}
        """))
    config, found = read_config(path, environ={})
    assert config is not None and not found.items, [str(p) for p in found.items]
    assert config.servers[0].address("0.0.0.0:41234") == "robot.local:41234"
    assert config.components[0].remote and config.remote_components == config.components


def test_hosts_section_mistakes(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        hosts:
          local: 10.0.0.2:7070
          arm: not-an-address
          leg: {agnet: "10.0.0.3:7070"}
          hand: {agent: "10.0.0.4:7070"}
        servers:
          main: {listen: "10.0.0.1:0", subarchitectures: [vision], host: hand}
        subarchitectures:
          vision:
            components:
              a: {class: "m:A", in_process: true, host: hand}
              b: {class: "m:B", host: leg}
        """)
    one(found, 2, "hosts.local", "'local' is the orchestrator's own host")
    one(found, 3, "hosts.arm", "HOST:PORT")
    one(found, 4, "hosts.leg.agnet", "did you mean 'agent'?")
    one(found, 7, "servers.main.host", "is the directory (the first server), which runs on the orchestrator's host")
    one(found, 11, "components.a.host", "an in_process component runs inside its server")
    assert not [p for p in found if "unknown host" in p.message]  # leg's entry was reported, not each use


def test_cast_check_describes_the_hosts_and_probe_says_an_agent_is_down(tmp_path: Path) -> None:
    path = tmp_path / "system.yaml"
    path.write_text(textwrap.dedent(f"""\
        python_path: [{COMPONENTS}]
        hosts: {{arm: "127.0.0.1:1"}}
        servers:
          main: {{listen: "10.0.0.1:0", subarchitectures: [vision]}}
        subarchitectures:
          vision:
            components:
              producer: {{class: orch_components:Producer, host: arm}}
              worker: {{kind: managed, class: orch_components:Worker}}
        """))
    env = {k: v for k, v in os.environ.items() if not k.startswith("CAST_")}
    done = subprocess.run([CAST, "check", "system.yaml"], capture_output=True, text=True, cwd=tmp_path, env=env)
    assert done.returncode == 0, done.stderr
    assert "hosts: local (1 component), arm (1 component)" in done.stdout
    probed = subprocess.run([CAST, "check", "system.yaml", "--probe"], capture_output=True, text=True, cwd=tmp_path,
                            env=dict(env, CAST_SECRET="s" * 32))
    assert probed.returncode == 1
    assert "system.yaml:8: error: components.producer.host: agent not usable: host 'arm' (agent 127.0.0.1:1): " \
           "UNAVAILABLE" in probed.stderr, probed.stderr


def test_a_variable_may_stand_for_an_agents_address_or_its_port(tmp_path: Path) -> None:
    text = """\
        hosts:
          arm: "${ARM_AGENT}"
          leg: "10.0.0.3:${LEG_PORT:-7070}"
        servers:
          main: {listen: "10.0.0.1:0", subarchitectures: [vision]}
        subarchitectures:
          vision:
            components:
              a: {class: "m:A", host: arm}
              b: {class: "m:B", host: leg}
        """
    # Editors check the file as written, where the variable is not known: the schema lets it stand.
    raw = yaml.safe_load(textwrap.dedent(text))
    assert not list(Draft7Validator(system_schema()).iter_errors(raw))
    path = tmp_path / "system.yaml"
    path.write_text(textwrap.dedent(text))
    config, found = read_config(path, environ={"ARM_AGENT": "10.0.0.2:7071"})
    assert config is not None and not found.items, [str(p) for p in found.items]
    assert (config.hosts["arm"].agent, config.hosts["leg"].agent) == ("10.0.0.2:7071", "10.0.0.3:7070")
    # cast check sees the value: a variable without a port is still reported on its line.
    _, wrong = read_config(path, environ={"ARM_AGENT": "10.0.0.2"})
    one(wrong.items, 2, "hosts.arm", "HOST:PORT")


def test_a_remote_server_started_later_with_port_0_is_reported_on_the_earlier_ones_line(tmp_path: Path) -> None:
    found = problems(tmp_path, """\
        hosts: {arm: "10.0.0.2:7070", leg: "10.0.0.3:7070"}
        servers:
          main: {listen: "10.0.0.1:0", subarchitectures: [a]}
          first: {listen: "10.0.0.2:0", host: arm, subarchitectures: [b]}
          second: {listen: "10.0.0.3:0", host: leg, subarchitectures: [c]}
        subarchitectures: {a: {}, b: {}, c: {}}
        """)
    one(found, 4, "servers.first.host", "starts before server 'second' (host 'leg') and must be told its address")
    assert len(found) == 1, [str(p) for p in found]
