"""The live view: the recorder's resuming watch loop feeding a :class:`FoxgloveSink` instead of a file.

:class:`LiveView` attaches to a running system like ``cast record`` does (the
same :class:`Recorder`, so a reconnect or a restarted server loses nothing and
a lost stretch of history is marked on ``/cast/gaps`` and shown in the app),
announces at once the channels a viewer will want (``/cast/changes``,
``/cast/gaps``, each watched SA's ``cast.v1.Task`` decisions and every type
present in its working memory), and then every channel as its type first
changes. :class:`BackgroundView` runs one on a thread, for ``cast run --foxglove``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import grpc

from cast.client.channel import ServerLink, map_rpc_error
from cast.client.credentials import ClientTls, TokenSource
from cast.core.records import TASK_TYPE
from cast.errors import CastError
from cast.foxglove.sink import FoxgloveSink
from cast.recording.channels import Gap
from cast.recording.recorder import Recorder, RecordOptions
from cast.v1 import inspection_pb2 as insp_pb2
from cast.v1 import inspection_pb2_grpc as insp_grpc

__all__ = ["VIEW_ID", "BackgroundView", "LiveView", "ViewOptions"]

VIEW_ID = "cast-foxglove"
"""The identity the live view reads under (a reader: it writes nothing)."""


@dataclass(frozen=True)
class ViewOptions:
    """What to show: SAs (empty: every SA) and entry types (empty: every type)."""

    subarchitectures: tuple[str, ...] = ()
    types: tuple[str, ...] = ()


Notice = Callable[[str], None]


class LiveView:
    """One system's working memories served on a :class:`FoxgloveSink` as they change.

    Construction asks the directory about the system (the named error if it
    does not answer or an SA is unknown); :meth:`start` creates the watches
    and announces the channels known now; :meth:`run` serves changes until
    told to stop.
    """

    def __init__(self, sink: FoxgloveSink, endpoint: str, tokens: TokenSource, options: ViewOptions,
                 tls: ClientTls | None = None, notice: Notice | None = None) -> None:
        self.sink = sink
        self.options = options
        self._tokens = tokens
        self._tls = tls
        self._notice = notice or (lambda _text: None)
        self.recorder = Recorder(endpoint, tokens, RecordOptions(options.subarchitectures, options.types), tls)
        self.endpoint = endpoint

    @property
    def subarchitectures(self) -> list[str]:
        """The SAs shown."""
        return list(self.recorder.subarchitectures)

    @property
    def system_name(self) -> str:
        """The name of the system shown."""
        return str(self.recorder.system.name)

    def start(self) -> None:
        """Watch from now on, then announce the channels of what the working memories hold already."""
        self.recorder.start()  # first, so that no type written meanwhile is missed: it arrives as a change
        for sa in self.recorder.subarchitectures:
            for type_name in self._present_types(sa):
                if not self.options.types or type_name in self.options.types:
                    self.sink.announce(self.recorder.channels.channel(sa, type_name))

    def _present_types(self, sa: str) -> list[str]:
        """Task decisions and the types of the entries an SA holds now (sorted), as far as its server tells."""
        link = ServerLink(self._endpoint_of(sa), self._tls)
        try:
            listing = insp_grpc.InspectionStub(link.channel).ListEntries(
                insp_pb2.ListEntriesRequest(subarchitecture=sa), metadata=self._tokens.metadata(), timeout=10)
            present = {entry.type for entry in listing.entries}
        except grpc.RpcError as exc:
            # Only a head start for the viewer: the channels still appear with the first change.
            self._notice(f"cannot list the entries of '{sa}' ({map_rpc_error(exc).message}): its channels appear "
                         "as its entries change")
            present = set()
        finally:
            link.close()
        return sorted(present | {TASK_TYPE})

    def _endpoint_of(self, sa: str) -> str:
        system = self.recorder.system
        info = next(i for i in system.subarchitectures if i.name == sa)
        return info.endpoint if info.endpoint and info.endpoint != system.endpoint else self.endpoint

    def run(self, stop: threading.Event) -> None:
        """Serve changes until ``stop`` is set (or the recorder's loop ends); then close the watches."""
        self.recorder.run(self.sink, stop, None, self._gap)

    def _gap(self, gap: Gap) -> None:
        text = gap.describe().replace("are not recorded", "were not shown")
        self.sink.warn(text)
        self._notice(text)

    @property
    def stop_reason(self) -> str:
        """Why :meth:`run` ended on its own (empty when it was told to stop)."""
        return self.recorder.stop_reason

    def close(self) -> None:
        """End the watches (the sink stays: its owner closes it)."""
        self.recorder.close()


class BackgroundView:
    """A :class:`LiveView` on its own thread, as ``cast run --foxglove`` keeps one beside its servers."""

    def __init__(self, view: LiveView) -> None:
        self.view = view
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._body, name="cast-foxglove", daemon=True)
        self.error: BaseException | None = None

    def _body(self) -> None:
        try:
            self.view.run(self._stop)
        except Exception as exc:  # noqa: BLE001 - kept for the owner, who says it; a thread would only print it
            self.error = exc

    @classmethod
    def start(cls, sink: FoxgloveSink, endpoint: str, tokens: TokenSource, tls: ClientTls | None,
              notice: Notice) -> BackgroundView:
        """Attach to the system at ``endpoint`` and serve it on a new thread; the named error if it cannot attach."""
        view = LiveView(sink, endpoint, tokens, ViewOptions(), tls, notice)
        try:
            view.start()
        except CastError:
            view.close()
            raise
        background = cls(view)
        background._thread.start()
        return background

    def stop(self, timeout: float = 10.0) -> None:
        """Stop serving changes and wait for the thread (the sink stays open: its owner closes it)."""
        self._stop.set()
        self._thread.join(timeout)
