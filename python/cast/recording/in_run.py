"""``cast run --record FILE``: a recording of the whole run, made by the orchestrator beside its servers.

The file is checked before anything starts (it must not exist; its directory
must); attached before any component starts, the file holds every change from
the first, and it is finished (summary and indexes) on every way out. The
steps are those of every attached tool (:mod:`cast.attach`).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path

from cast.attach import AttachedTool
from cast.client.credentials import ClientTls, TokenSource
from cast.errors import CastError, InvalidArgumentError
from cast.recording.channels import Gap
from cast.recording.mcap_file import RecordingWriter
from cast.recording.recorder import RECORD_ID, Recorder, RecordOptions

__all__ = ["RunRecording"]


class RunRecording(AttachedTool):
    """The recording of one ``cast run``: checked at construction, then attached, stopped and closed."""

    tool_id = RECORD_ID

    def __init__(self, path: Path, notice: Callable[[str], None]) -> None:
        if path.exists():
            raise InvalidArgumentError(f"--record {path}: the file exists; give another name, or remove it first "
                                       "(a recording is never overwritten)")
        if not path.parent.is_dir():
            raise InvalidArgumentError(f"--record {path}: no directory {path.parent}")
        super().__init__(notice)
        self.path = path
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._recorder: Recorder | None = None
        self._writer: RecordingWriter | None = None
        self.error: str = ""

    def _start(self, endpoint: str, tokens: TokenSource, tls: ClientTls | None) -> None:
        recorder = Recorder(endpoint, tokens, RecordOptions(), tls)
        recorder.start()
        self._recorder = recorder
        self._writer = RecordingWriter(self.path, recorder.header())
        self._thread = threading.Thread(target=self._run, name="cast-run-record", daemon=True)
        self._thread.start()
        self._notice(f"recording every change of {', '.join(recorder.subarchitectures)} to {self.path}")

    def _not_started(self, why: str) -> str:
        return f"not recording to {self.path}: {why}"

    def _run(self) -> None:
        assert self._recorder is not None and self._writer is not None

        def gap(found: Gap) -> None:
            self._notice(f"the recording has a gap: {found.describe()}")

        try:
            self._recorder.run(self._writer, self._stop, None, gap)
        except CastError as exc:
            self.error = exc.message

    def stop_watching(self) -> None:
        """Stop recording (the components have stopped) and finish the file; say what it holds."""
        recorder, writer = self._recorder, self._writer
        if recorder is None or writer is None:
            return
        self._recorder = None
        recorder.stop_reason = recorder.stop_reason or "cast run stopped"
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        recorder.close()
        writer.finish(recorder.trailer())
        gaps = f", {len(recorder.stats.gaps)} gap(s)" if recorder.stats.gaps else ""
        failed = f"; the recorder failed: {self.error}" if self.error else ""
        self._notice(f"recorded {recorder.stats.changes} changes to {self.path}{gaps}{failed} (`cast info "
                     f"{self.path}`)")

    def close(self) -> None:
        """Finish the file if that has not happened (an error path)."""
        self.stop_watching()
