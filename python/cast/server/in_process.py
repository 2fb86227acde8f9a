"""Python components that run inside the server's process (``in_process: true``).

Each gets a :class:`~cast.client.local_transport.LocalTransport` and its own
thread; the API and the guarantees are those of a remote component.
"""

from __future__ import annotations

import logging
import threading

from cast.client.local_transport import LocalTransport
from cast.client.runner import load_component_class, run_component
from cast.config import ComponentConfig
from cast.core.records import Identity
from cast.core.system import System

__all__ = ["InProcessComponents"]

log = logging.getLogger("cast.server")


class InProcessComponents:
    """Starts and stops the in-process components of a system."""

    def __init__(self, system: System) -> None:
        self._system = system
        self._running: list[tuple[ComponentConfig, threading.Thread, object]] = []
        self.exit_codes: dict[str, int] = {}

    def start(self, config: ComponentConfig) -> None:
        """Start one component on its own thread."""
        if config.language != "python":
            raise ValueError(f"component '{config.id}': only Python components can run in process")
        cls = load_component_class(config.cls)
        component = cls()
        transport = LocalTransport(self._system, Identity(config.id, config.subarchitecture, config.privileged))

        def body() -> None:
            # In the start barrier like every component: the server's own barrier says whether to wait.
            self.exit_codes[config.id] = run_component(
                component, transport, dict(config.args), handle_signals=False, barrier=True
            )

        thread = threading.Thread(target=body, name=f"cast-inproc-{config.id}", daemon=True)
        thread.start()
        self._running.append((config, thread, component))

    def stop_all(self, timeout: float = 10.0) -> None:
        """Ask every component to stop (reverse start order) and wait for them."""
        for config, thread, component in reversed(self._running):
            component.request_stop()  # type: ignore[attr-defined]
            thread.join(timeout)
            if thread.is_alive():
                log.error("in-process component '%s' did not stop within %s s", config.id, timeout)
        self._running.clear()
