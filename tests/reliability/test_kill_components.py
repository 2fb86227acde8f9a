"""Kill -9 of random components of a running system under load (run by the orchestrator).

Churners do locked read-modify-writes and hold tasks; an auditor checks every change.
Random churners are SIGKILLed; the orchestrator restarts them; the server released
their locks and tasks; the system keeps running; no component sees an inconsistent
entry. 6 kills in `make test`, 40 in `make soak`.
"""

from __future__ import annotations

import os
import random
import signal
import time
from pathlib import Path
from typing import Any

from google.protobuf.wrappers_pb2 import Int64Value, StringValue

from cast.core.records import Identity
from cast.orchestrator.supervisor import Phase
from tests.orchestrator.conftest import Embedded, embedded  # noqa: F401 - the fixture
from tests.orchestrator.conftest import write_config as write_orch_config
from tests.reliability.conftest import wait_for
from tests.reliability.figures import record, soak

COMPONENTS = Path(__file__).resolve().parent / "components"


def _versions(host: Any, who: Identity) -> int:
    """Overwrites of the shared entries so far (versions count from the server's version floor)."""
    keys = [f"shared-{k}" for k in range(3)]
    return sum(host.get(who, "work", key).version - host.version_floor for key in keys
               if host.exists(who, "work", key))


def test_killing_random_components_releases_their_locks_and_tasks_and_the_system_runs_on(
    tmp_path: Path, embedded: Any  # noqa: F811 - the fixture imported above
) -> None:
    churners = [f"churner{i}" for i in range(3)]
    restart = {"policy": "always", "max_restarts": 1000, "backoff": 0.05, "max_backoff": 0.2}
    cfg = write_orch_config(tmp_path / "kill.yaml", {
        "python_path": [str(COMPONENTS)],
        "system": "kill",
        "subarchitectures": {"work": {
            "task_manager": {"policy": "fifo", "max_concurrent": 2},
            "components": {
                **{c: {"kind": "managed", "class": "rel_components:Churner", "restart": restart} for c in churners},
                "auditor": {"class": "rel_components:Auditor"},
            },
        }},
    })
    run: Embedded = embedded(cfg)
    system = run.system("work")
    host, who = system.host, Identity("test", "work")
    sup = run.orchestrator.supervisor
    assert sup is not None
    rng = random.Random(7)
    kills = 40 if soak() else 6
    wait_for(lambda: _versions(host, who) > 20, what="the churners to work")
    # The first victim holds a live task (a waiting one stays so until adopted, an adopted one 0.5 s),
    # so that one kill at least is seen releasing a task, however slowly the churners get going.
    wait_for(lambda: system.tasks.tasks("work"), what="a churner to hold a task")
    first = system.tasks.tasks("work")[0].component
    for kill in range(kills):
        victim = first if kill == 0 else rng.choice(churners)
        wait_for(lambda v=victim: sup.components[v].pid and sup.components[v].phase is Phase.RUNNING,
                 what=f"{victim} to run")
        os.kill(sup.components[victim].pid, signal.SIGKILL)
        time.sleep(rng.uniform(0.2, 0.8))
    # Every churner is back and registered, and the work goes on.
    wait_for(lambda: all(sup.components[c].phase is Phase.RUNNING for c in churners), what="restarts")
    wait_for(lambda: all(i.session_id for i in system.sessions.components() if i.id in churners), what="sessions")
    before = _versions(host, who)
    wait_for(lambda: _versions(host, who) > before + 20, what="progress after the kills")
    # Locks and tasks are held only by live sessions (a killed incarnation's were released).
    sessions = {c.id: c for c in system.sessions.components()}
    for k in range(3):
        holder = host.lock_holder("work", f"shared-{k}")
        assert holder is None or sessions[holder[0]].session_id, holder
    for task in system.tasks.tasks("work"):
        assert sessions[task.component].session_id, task
    assert system.tasks.counters["work"]["retracted"] >= 1  # killed holders' tasks went
    # No component saw an inconsistent entry, and every shared entry is consistent now.
    wait_for(lambda: int(host.get(who, "work", "audit").data and
                         StringValue.FromString(host.get(who, "work", "audit").data).value.split()[0]) > 50,
             what="the auditor to check")
    checked, violations = map(int, StringValue.FromString(host.get(who, "work", "audit").data).value.split())
    assert violations == 0
    for k in range(3):
        record_k = host.get(who, "work", f"shared-{k}")
        assert Int64Value.FromString(record_k.data).value == record_k.version - host.version_floor
    restarts = sum(sup.components[c].restarts for c in churners)
    run.stop()
    assert restarts >= kills
    record("kill_components", {"kills": kills, "restarts": restarts, "changes_audited": checked,
                               "inconsistent": violations,
                               "tasks_retracted": system.tasks.counters["work"]["retracted"]})
