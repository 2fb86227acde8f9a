"""Which credential each call of the wire API needs: one table, read by every servicer.

The servicers look their call up here before anything else (``cast.server.rpc``), and the agent's
interceptor does the same for its service, so whether a call may go without a token is decided in
one place; ``tests/integration/test_calls.py`` fails when a call of a ``cast.v1`` service has no entry.
Calls are named as gRPC names them on the wire: ``cast.v1.<Service>/<Method>``.
"""

from __future__ import annotations

from enum import Enum

__all__ = ["CALLS", "Credential", "credential"]


class Credential(Enum):
    """What a caller must show."""

    TOKEN = "a component's token"
    """A token signed with the system's secret (``cast token``, the orchestrator, an agent)."""

    READ = "a token, or none where the configuration says auth.reads_require_token: false"
    """Reads: open to anyone the configuration lets read without a token (as ``anonymous``); a bad token is
    refused all the same."""

    ORCHESTRATOR = "the orchestrator's privileged token, or a client certificate of the agent's CA"
    """The agent's calls: they start processes on the agent's host."""


_T, _R, _O = Credential.TOKEN, Credential.READ, Credential.ORCHESTRATOR

CALLS: dict[str, Credential] = {
    # Writes and locks change a WM; they carry the writer's identity.
    "cast.v1.WorkingMemory/Add": _T,
    "cast.v1.WorkingMemory/Overwrite": _T,
    "cast.v1.WorkingMemory/Delete": _T,
    "cast.v1.WorkingMemory/Batch": _T,
    "cast.v1.WorkingMemory/Lock": _T,
    "cast.v1.WorkingMemory/Unlock": _T,
    "cast.v1.WorkingMemory/Write": _T,
    "cast.v1.WorkingMemory/Get": _R,
    "cast.v1.WorkingMemory/GetByType": _R,
    "cast.v1.WorkingMemory/Exists": _R,
    "cast.v1.WorkingMemory/Watch": _R,
    # Tasks belong to the proposer's session; only the listing is a read.
    "cast.v1.TaskManager/Propose": _T,
    "cast.v1.TaskManager/Retract": _T,
    "cast.v1.TaskManager/Complete": _T,
    "cast.v1.TaskManager/Decisions": _T,
    "cast.v1.TaskManager/ListTasks": _R,
    # Sessions are a component's; schemas are checked and kept for the system.
    "cast.v1.Directory/DescribeSystem": _R,
    "cast.v1.Directory/Register": _T,
    "cast.v1.Directory/Heartbeat": _T,
    "cast.v1.Directory/AwaitRun": _T,
    "cast.v1.Directory/RegisterSchemas": _T,
    "cast.v1.Directory/GetSchema": _R,
    # Tools read; a reported outcome is filed under the reporter's identity.
    "cast.v1.Inspection/ListEntries": _R,
    "cast.v1.Inspection/TaskStatistics": _R,
    "cast.v1.Inspection/GetMetrics": _R,
    "cast.v1.Inspection/Report": _T,
    # The agent starts and stops processes for its orchestrator.
    "cast.v1.Agent/Attach": _O,
    "cast.v1.Agent/Launch": _O,
    "cast.v1.Agent/Stop": _O,
    "cast.v1.Agent/Probe": _O,
    "cast.v1.Agent/Renew": _O,
}
"""Every call of the ``cast.v1`` services and the credential it needs."""


def credential(call: str) -> Credential:
    """The credential ``call`` (``cast.v1.Service/Method``) needs; KeyError for a call the table lacks."""
    return CALLS[call]
