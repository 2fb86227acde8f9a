"""Who a test acts as, and the components it runs.

- :class:`Actor`: the test acting as another component (``act_as("camera",
  "vision")``): every working-memory call of a component, and tasks, whose
  decisions it keeps.
- :class:`RunningComponent`: a component under test, driven by the runner's own
  lifecycle (configure, start, run on a thread of its own, stop once), as
  ``python -m cast.run`` drives it.
"""

from __future__ import annotations

import threading
from typing import Any, Generic, TypeVar

from cast.client.component import Component, ManagedComponent
from cast.client.runner import run_component
from cast.client.transport import Transport
from cast.client.types import Task
from cast.testing.waiting import DEFAULT_TIMEOUT_S, wait_for

__all__ = ["Actor", "RunningComponent"]

C = TypeVar("C", bound=Component)


class Actor(ManagedComponent):
    """A test acting as a component: its writes are that component's, and so are its tasks.

    Every call of a component (``add``, ``overwrite``, ``get``, ``lock``,
    ``on_change``, ``propose_task``, ...) with that component's identity and
    rights. The task manager's decisions about its tasks are kept in
    :attr:`decisions`; :meth:`wait_for_decision` waits for one.
    """

    def __init__(self) -> None:
        super().__init__()
        self._decided: list[Task] = []
        self._decided_lock = threading.Lock()

    def task_adopted(self, task: Task) -> None:
        """Kept in :attr:`decisions`."""
        with self._decided_lock:
            self._decided.append(task)

    def task_rejected(self, task: Task) -> None:
        """Kept in :attr:`decisions`."""
        with self._decided_lock:
            self._decided.append(task)

    @property
    def decisions(self) -> list[Task]:
        """The decisions about this actor's tasks so far (adopted or rejected), in the order they came."""
        with self._decided_lock:
            return list(self._decided)

    def wait_for_decision(self, task: Task | str, timeout: float = DEFAULT_TIMEOUT_S) -> Task:
        """The task as its task manager decided it (ADOPTED or REJECTED); fails after ``timeout`` seconds."""
        task_id = task if isinstance(task, str) else task.task_id

        def decided() -> Task:
            found = next((t for t in self.decisions if t.task_id == task_id), None)
            assert found is not None, f"decisions so far: {self.decisions or 'none'}"
            return found

        return wait_for(decided, timeout, f"the decision about task {task_id} of {self.component_id}")

    def close(self) -> None:
        """End the session (its locks and tasks are released) and close the connection."""
        self.request_stop()
        self._cast_close()

    def __enter__(self) -> Actor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RunningComponent(Generic[C]):
    """A component under test running its lifecycle on a thread: configure, start, run; stop once at the end.

    :meth:`cast.testing.LocalSystem.run` returns it once ``start()`` returned,
    so the component's watches are registered: nothing the test writes after
    that is missed.
    """

    def __init__(self, component: C, transport: Transport, args: dict[str, Any]) -> None:
        self.component = component
        """The component object (its attributes are the test's to read)."""
        self.exit_code: int | None = None
        """0 after a clean stop, 1 when a hook raised (the runner's exit codes); None while it runs."""
        self.component_id = transport.identity.component_id
        """The component's id."""
        self._started = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._body, args=(transport, args), daemon=True,
                                        name=f"cast-testing-{self.component_id}")
        self._thread.start()

    def _body(self, transport: Transport, args: dict[str, Any]) -> None:
        try:
            self.exit_code = run_component(self.component, transport, args, handle_signals=False,
                                           started=self._started.set)
        except Exception as exc:  # noqa: BLE001 - binding failed (a refused token, ...): the test hears of it
            self._error = exc
            self.exit_code = 1
        finally:
            self._started.set()

    def wait_started(self, timeout: float) -> None:
        """Wait until ``start()`` returned (or the lifecycle ended); raise what binding raised."""
        if not self._started.wait(timeout):
            raise AssertionError(f"{self.component_id}: start() did not return within {timeout:g} s")
        if self._error is not None:
            raise self._error

    @property
    def running(self) -> bool:
        """Whether its lifecycle is still going (it was not stopped and did not fail)."""
        return self._thread.is_alive()

    def join(self, timeout: float = DEFAULT_TIMEOUT_S) -> int:
        """Wait until the component stops by itself (``request_stop()``, a failed hook); its exit code."""
        self._thread.join(timeout)
        if self._thread.is_alive():
            raise AssertionError(f"{self.component_id} did not stop by itself within {timeout:g} s")
        assert self.exit_code is not None
        return self.exit_code

    def stop(self, timeout: float = DEFAULT_TIMEOUT_S) -> int:
        """Ask the component to stop (stop() is called once) and wait for its end; its exit code.

        0 after a clean stop, 1 when a hook raised: assert it, so that a component that failed
        quietly fails the test.
        """
        if self._thread.is_alive():
            self.component.request_stop()
        return self.join(timeout + 15.0)  # the runner gives run() 10 s and the callbacks 5 s after stop()
