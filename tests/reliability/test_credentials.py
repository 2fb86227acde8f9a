"""Credentials: every RPC refuses missing, malformed, forged and expired tokens; A cannot act as B;
reads may be opened by configuration; expiring tokens are renewed by the orchestrator."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import grpc
import pytest
from cast_testing_pb2 import Counter
from google.protobuf import any_pb2

import cast
from cast.auth import TokenSigner
from cast.client.credentials import TokenSource
from cast.client.grpc_transport import GrpcTransport
from cast.core.records import Identity, LockMode
from cast.v1 import (
    directory_pb2,
    directory_pb2_grpc,
    entry_pb2,
    task_manager_pb2,
    task_manager_pb2_grpc,
    working_memory_pb2,
    working_memory_pb2_grpc,
)
from tests.conftest import ServerHandle, renewing_token_file
from tests.orchestrator.conftest import Embedded, embedded  # noqa: F401 - the fixture, used below
from tests.orchestrator.conftest import write_config as write_orch_config
from tests.reliability.conftest import wait_for
from tests.reliability.rawcalls import call, methods

COMPONENTS = Path(__file__).resolve().parent / "components"


def _bad_tokens(server: ServerHandle) -> dict[str, Any]:
    good = server.token("a", "vision")
    body, _, sig = good.partition(".")
    other_secret = TokenSigner(b"another-system-secret-0123456789").issue(Identity("a", "vision"))
    expired = server.signer.issue(Identity("a", "vision"), ttl_seconds=-10)  # expired ten seconds ago
    return {
        "missing": (),
        "not bearer": (("authorization", f"Basic {good}"),),
        "malformed": (("authorization", "Bearer not-a-token"),),
        "altered": (("authorization", f"Bearer {body}x.{sig}"),),
        "other secret": (("authorization", f"Bearer {other_secret}"),),
        "expired": (("authorization", f"Bearer {expired}"),),
    }


def test_every_rpc_refuses_bad_tokens_with_unauthenticated(server: ServerHandle) -> None:
    channel = grpc.insecure_channel(server.endpoint)
    tried = 0
    try:
        for label, md in _bad_tokens(server).items():
            for method in methods():
                code, details, _ = call(channel, method, [b""], md)
                assert code == grpc.StatusCode.UNAUTHENTICATED, (label, method.path, code, details)
                tried += 1
        # The token checks say what to do.
        code, details, _ = call(channel, methods()[0], [b""], ())
        assert "no token" in details and "CAST_TOKEN" in details
    finally:
        channel.close()
    assert tried == 6 * len(methods())


def _stubs(server: ServerHandle, who: str) -> tuple[Any, Any, Any, Any]:
    ch = grpc.insecure_channel(server.endpoint)
    md = (("authorization", f"Bearer {server.token(who, 'vision')}"),)
    return (ch, md, working_memory_pb2_grpc.WorkingMemoryStub(ch), task_manager_pb2_grpc.TaskManagerStub(ch))


def _code(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> grpc.StatusCode:
    with pytest.raises(grpc.RpcError) as info:
        fn(*args, **kwargs)
    return info.value.code()


def test_a_token_of_a_cannot_touch_the_session_tasks_or_locks_of_b(server: ServerHandle) -> None:
    cha, mda, wma, tma = _stubs(server, "a")
    chb, mdb, wmb, tmb = _stubs(server, "b")
    try:
        dir_a, dir_b = directory_pb2_grpc.DirectoryStub(cha), directory_pb2_grpc.DirectoryStub(chb)
        # B's session: A cannot heartbeat it (PERMISSION_DENIED), and B's session goes on.
        session = dir_b.Register(directory_pb2.RegisterRequest(language="python"), metadata=mdb).session_id
        beats = dir_a.Heartbeat(iter([directory_pb2.HeartbeatRequest(session_id=session)]), metadata=mda)
        assert _code(list, beats) == grpc.StatusCode.PERMISSION_DENIED
        # B's task (B's session is live: A's refused heartbeat did not end it): A can neither retract nor
        # complete it.
        task = tmb.Propose(task_manager_pb2.ProposeRequest(name="b-work"), metadata=mdb).task
        assert _code(tma.Retract, task_manager_pb2.RetractRequest(task_id=task.task_id), metadata=mda) == \
            grpc.StatusCode.PERMISSION_DENIED
        req = task_manager_pb2.CompleteRequest(task_id=task.task_id, outcome=task_manager_pb2.TASK_OUTCOME_SUCCEEDED)
        assert _code(tma.Complete, req, metadata=mda) == grpc.StatusCode.PERMISSION_DENIED
        live = tmb.ListTasks(task_manager_pb2.ListTasksRequest(subarchitecture="vision"), metadata=mdb).tasks
        assert [t.task_id for t in live] == [task.task_id]
        # B's lock: A cannot unlock it, overwrite or delete the entry, nor take the lock.
        addr = entry_pb2.EntryAddress(id="doc", subarchitecture="vision")
        value = any_pb2.Any()
        value.Pack(Counter(value=1))
        added = wmb.Add(working_memory_pb2.AddRequest(address=addr, value=value), metadata=mdb).version
        wmb.Lock(working_memory_pb2.LockRequest(address=addr, mode=LockMode.OD), metadata=mdb)
        fp = grpc.StatusCode.FAILED_PRECONDITION
        assert _code(wma.Unlock, working_memory_pb2.UnlockRequest(address=addr), metadata=mda) == fp
        assert _code(wma.Overwrite, working_memory_pb2.OverwriteRequest(address=addr, value=value), metadata=mda) == fp
        assert _code(wma.Delete, working_memory_pb2.DeleteRequest(address=addr), metadata=mda) == fp
        lock_req = working_memory_pb2.LockRequest(address=addr, mode=LockMode.O, no_wait=True)
        assert _code(wma.Lock, lock_req, metadata=mda) == fp
        # Nothing changed: B still holds the lock at depth 1, the entry is at the version it was added with.
        assert wmb.Unlock(working_memory_pb2.UnlockRequest(address=addr), metadata=mdb).depth == 0
        got = wmb.Get(working_memory_pb2.GetRequest(address=addr), metadata=mdb).entry
        assert (got.version, got.author) == (added, "b")
    finally:
        cha.close()
        chb.close()


def test_reads_without_a_token_when_the_configuration_opens_them(server_factory: Any) -> None:
    config = {"system": "open", "subarchitectures": {"vision": {}}, "auth": {"reads_require_token": False}}
    handle = server_factory(config)
    ch = grpc.insecure_channel(handle.endpoint)
    try:
        wm = working_memory_pb2_grpc.WorkingMemoryStub(ch)
        md = (("authorization", f"Bearer {handle.token('w', 'vision')}"),)
        addr = entry_pb2.EntryAddress(id="x", subarchitecture="vision")
        value = any_pb2.Any()
        value.Pack(Counter(value=3))
        assert _code(wm.Add, working_memory_pb2.AddRequest(address=addr, value=value)) == \
            grpc.StatusCode.UNAUTHENTICATED  # writes still need a token
        added = wm.Add(working_memory_pb2.AddRequest(address=addr, value=value), metadata=md).version
        assert wm.Get(working_memory_pb2.GetRequest(address=addr)).entry.version == added
        assert wm.Exists(working_memory_pb2.ExistsRequest(address=addr)).exists
        directory_pb2_grpc.DirectoryStub(ch).DescribeSystem(directory_pb2.DescribeSystemRequest())
        bad = (("authorization", "Bearer forged.token"),)
        assert _code(wm.Get, working_memory_pb2.GetRequest(address=addr), metadata=bad) == \
            grpc.StatusCode.UNAUTHENTICATED  # a bad token is refused even where none is needed
        lock = working_memory_pb2.LockRequest(address=addr, mode=LockMode.O)
        assert _code(wm.Lock, lock) == grpc.StatusCode.UNAUTHENTICATED
    finally:
        ch.close()


def test_an_expiring_token_renewed_through_its_file_keeps_the_component_working(
    server: ServerHandle, tmp_path: Path
) -> None:
    identity = Identity("renewed", "vision")
    fixed_id = Identity("fixed", "vision")
    with renewing_token_file(server.signer, identity, tmp_path / "renewed.token") as path:
        renewed = cast.UnmanagedComponent()
        renewed._cast_bind(GrpcTransport(server.endpoint, TokenSource(path.read_text(), path, 0.2), identity))
        fixed = cast.UnmanagedComponent()
        fixed._cast_bind(GrpcTransport(server.endpoint, server.signer.issue(fixed_id, ttl_seconds=2), fixed_id))
        try:
            renewed.add("r", Counter(value=0))
            fixed.add("f", Counter(value=0))
            deadline = time.monotonic() + 4.5  # well past the first tokens' expiry
            i = 0
            while time.monotonic() < deadline:
                i += 1
                renewed.overwrite("r", Counter(value=i))
                time.sleep(0.1)
            with pytest.raises(cast.UnauthenticatedError, match="expired"):
                fixed.overwrite("f", Counter(value=1))
        finally:
            renewed._cast_close()
            fixed._cast_close()

def test_the_orchestrator_renews_expiring_tokens_of_the_components_it_runs(
    tmp_path: Path, embedded: Any  # noqa: F811 - the fixture imported above
) -> None:
    cfg = write_orch_config(tmp_path / "ttl.yaml", {
        "python_path": [str(COMPONENTS)],
        "system": "ttl",
        "auth": {"token_ttl": 2},
        "subarchitectures": {"vision": {"components": {"ticker": {"class": "rel_components:Ticker"}}}},
    })
    run: Embedded = embedded(cfg)
    host = run.system("vision").host
    who = Identity("test", "vision")
    wait_for(lambda: host.exists(who, "vision", "tick"), what="the first tick")
    time.sleep(4.5)  # two token lifetimes: the first token has expired
    later = host.get(who, "vision", "tick").version
    wait_for(lambda: host.get(who, "vision", "tick").version > later + 5, what="ticks after the first token expired")
    assert run.orchestrator._security is not None and run.orchestrator._security.renewals >= 2
    assert not host.exists(who, "vision", "tick-error"), host.get(who, "vision", "tick-error").data
    result = run.stop()
    assert result.exit_code == 0, result.failures
