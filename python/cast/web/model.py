"""What the page shows, kept current: a poller thread asks the servers every second, the feed streams changes.

Each tick asks every server for its SAs, components, metrics and task
managers (the calls of ``cast components``, ``cast stats`` and ``cast tasks``)
and renders the page's state once, as JSON text shared by every browser
connected. Changes arrive between ticks on the feed's watch streams. Entries
and values are asked for when a browser wants them (the WM a person looks at,
the entry they clicked), never copied wholesale into the view.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from typing import Any

from cast.bridges.status import mapping_rows
from cast.errors import CastError
from cast.web.feed import ChangeFeed
from cast.web.rates import RateWindow, Sample
from cast.web.source import SystemSource
from cast.web.state import architecture, entries_json, entry_json, task_managers
from cast.web.values import ValueDecoder

__all__ = ["ENTRIES_SHOWN", "VALUE_SHOWN", "LiveModel"]

ENTRIES_SHOWN = 500
"""The most entries of one WM the page lists (the most recently written; a type filter finds older ones)."""
VALUE_SHOWN = 1 << 20
"""The largest value (bytes) the page renders as JSON."""


class LiveModel:
    """The page's state of one system, refreshed every ``interval`` seconds on a thread of its own."""

    def __init__(self, source: SystemSource, interval: float = 1.0,
                 notice: Callable[[str], None] | None = None) -> None:
        self.source = source
        self.feed = ChangeFeed(source)
        self.decoder = ValueDecoder(source)
        self._interval = interval
        self._notice = notice or (lambda _text: None)
        self._window = RateWindow()
        self._mutex = threading.Lock()
        self._state_text = "{}"
        self._version = 0
        self._error = ""
        self._totals: dict[str, int] = {}
        self._listed_types: dict[str, set[str]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="cast-web-poll", daemon=True)

    def start(self) -> None:
        """Watch, take the first state (the named error if the system does not answer), then poll on a thread."""
        self.feed.start()
        self.refresh()
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self._interval):
            try:
                self.refresh()
            except CastError as exc:
                why = self._why(exc)
                if why != self._error:
                    self._notice(f"cannot read the system: {why} (trying again every {self._interval:g} s)")
                with self._mutex:
                    self._error = why
                    self._version += 1

    def _why(self, exc: CastError) -> str:
        # The client's words for UNAVAILABLE speak to a writer ("a write ... may or may not have been applied").
        if exc.code == "UNAVAILABLE":
            return f"no answer from {self.source.endpoint} (has the system stopped?)"
        return exc.message

    def refresh(self) -> None:
        """Ask the servers once and render the state."""
        sas, components = self.source.describe()
        metrics = self.source.metrics()
        counters = self.source.task_counters()
        tasks = self.source.tasks()
        mappings = mapping_rows(self.source.bridge_statuses())
        self._window.add(Sample(time.monotonic(), {sa.name: sa.revision for sa in sas}, metrics))
        self.feed.poll()
        state = {
            "system": self.source.name, "endpoint": self.source.endpoint, "time": time.time(),
            "connected": self.feed.connected, "error": "", "metrics_enabled": metrics["enabled"],
            **architecture(sas, components, self._window, mappings),
            "tasks": task_managers(counters, tasks, metrics),
            "decisions": self.feed.decisions(),
        }
        text = json.dumps(state, separators=(",", ":"))
        with self._mutex:
            self._totals = {sa.name: sa.entries for sa in sas}
            if self._error:
                self._notice("reading the system again")
            self._state_text, self._error = text, ""
            self._version += 1

    def state(self) -> tuple[int, str]:
        """The state's number (it grows with every refresh) and its JSON text (with the last error, if any)."""
        with self._mutex:
            if not self._error:
                return self._version, self._state_text
            stale = json.loads(self._state_text)
            return self._version, json.dumps({**stale, "error": self._error, "connected": False})

    def entries(self, sa: str, type_name: str = "") -> dict[str, Any]:
        """The entries of one WM (of one type), newest first: at most :data:`ENTRIES_SHOWN` of them."""
        listing = self.source.entries(sa, type_name, ENTRIES_SHOWN)
        with self._mutex:
            listed = self._listed_types.setdefault(sa, set())
            if not type_name:
                listed.clear()
            listed.update(e.type for e in listing.entries)
            types = sorted(listed | self.feed.types(sa) | ({type_name} if type_name else set()))
            # A listing under the limit is the whole WM (exact now); else the count of the last refresh.
            complete = not type_name and len(listing.entries) < ENTRIES_SHOWN
            total = len(listing.entries) if complete else max(self._totals.get(sa, 0), len(listing.entries))
        return entries_json(sa, listing, total, ENTRIES_SHOWN, types)

    def value(self, sa: str, entry_id: str) -> dict[str, Any]:
        """One entry with its value rendered as JSON; NotFoundError if it is not there.

        A value over :data:`VALUE_SHOWN` bytes is not rendered (a browser would choke on megabytes of
        JSON): the page says how big it is and which command shows it.
        """
        entry = self.source.get(sa, entry_id)
        data = entry.value.value
        if len(data) > VALUE_SHOWN:
            return entry_json(entry, {"@type": entry.type, "@error": (
                f"a value of {len(data):,} bytes: more than the {VALUE_SHOWN:,} this page shows; `cast get {sa} "
                f"{entry_id}` prints it")})
        return entry_json(entry, self.decoder.to_json(sa, entry.type, data))

    def close(self) -> None:
        """Stop polling and watching, close the connections. Once; later calls do nothing."""
        if self._stop.is_set():
            return
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(10)
        self.feed.close()
        self.source.close()
