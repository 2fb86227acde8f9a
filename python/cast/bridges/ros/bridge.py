"""The ROS bridge component: its mappings both ways, their buffers, and its status entry.

A ROS generation plugs in as a :class:`RosSide` (``ros2.Ros2Side``,
``ros1.Ros1Side``); everything else is the same for both:

- **ROS -> WM** (``to_wm``): the ROS callback only takes the message (and its
  receive time) into the mapping's outbox; a writer thread per mapping
  converts and writes it. ``store: latest`` keeps one message waiting (a newer
  one replaces it: a slow WM sees the current state, never a queue of old
  ones); ``store: each`` keeps up to ``buffer`` in order. A write the server
  cannot answer (it is away, restarting) is tried again until it is
  acknowledged, so nothing the bridge took from ROS is lost while the server
  is away, up to the buffer; what a full buffer drops is counted.
- **WM -> ROS** (``to_ros``): a watch per mapping; each ADD and OVERWRITE is
  converted and published. The client library resumes the watch after a
  reconnect, so changes made while the bridge was cut off are published
  when it is back. The bridge's own writes are never published back.
- A value that does not fit (``ConversionError``) is refused, counted and
  named in the status with its topic, field and limit; the bridge goes on.
- **Status**: every ``status_period`` the bridge overwrites a
  ``cast.v1.BridgeStatus`` entry ``<id>.status`` in its own SA (counts, rate,
  errors, ROS -> WM latency), which ``cast components``, ``cast stats`` and
  the web view show.
"""

from __future__ import annotations

import collections
import json
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from google.protobuf import message
from google.protobuf.timestamp_pb2 import Timestamp

import cast
from cast.bridges.ros.catalog import TypeCatalog
from cast.bridges.ros.convert import ConversionError, Converter
from cast.bridges.ros.model import RosTypeError
from cast.config.ros import RosBridgeConfig, RosQos, RosToWm, WmToRos
from cast.v1 import bridge_pb2

__all__ = ["RosBridge", "RosSide", "settings_from"]

log = logging.getLogger(__name__)

RETRY_S = 0.2  # between tries of a write the server could not answer
LATENCIES_KEPT = 1000


class RosSide(Protocol):
    """What the bridge needs of one ROS generation's client library."""

    middleware: str
    node_name: str

    def subscribe(self, topic: str, cls: Any, qos: RosQos, callback: Callable[[Any], None]) -> None:
        """Call ``callback(message)`` for each message of ``topic`` (on a ROS thread)."""

    def advertise(self, topic: str, cls: Any, qos: RosQos) -> Callable[[Any], None]:
        """A function that publishes one message on ``topic``."""

    def poll(self) -> bool:
        """Called every status period: True when ROS was found gone and the mappings registered again."""

    def close(self) -> None:
        """Leave ROS: end subscriptions, publishers and the node."""


def settings_from(args: dict[str, Any]) -> RosBridgeConfig:
    """The bridge's settings: ``args["ros"]`` when given, else ``$CAST_ROS_BRIDGE`` (set by ``cast run``)."""
    raw = args.get("ros")
    if raw is None:
        text = os.environ.get("CAST_ROS_BRIDGE", "")
        if not text:
            raise cast.InvalidArgumentError("the ROS bridge has no mappings: start it with `cast run` (language: ros "
                                            "and a ros: section) or give CAST_ROS_BRIDGE (docs/ros.md)")
        raw = json.loads(text)
    return RosBridgeConfig.from_dict(raw)


def _timestamp(seconds: float) -> Timestamp:
    ts = Timestamp()
    ts.FromNanoseconds(int(seconds * 1e9))
    return ts


def _stamp_seconds(ros_message: Any) -> float:
    """The header stamp of a message in seconds (0: none), for ROS 2 (sec, nanosec) and ROS 1 (secs, nsecs)."""
    stamp = getattr(getattr(ros_message, "header", None), "stamp", None)
    if stamp is None:
        return 0.0
    if hasattr(stamp, "sec"):
        return float(stamp.sec) + float(stamp.nanosec) * 1e-9
    return float(getattr(stamp, "secs", 0)) + float(getattr(stamp, "nsecs", 0)) * 1e-9


@dataclass
class _Stats:
    """What one mapping did; read by the status writer, written by the ROS and writer threads."""

    received: int = 0
    delivered: int = 0
    dropped: int = 0
    errors: int = 0
    last_error: str = ""
    last_error_time: float = 0.0
    last_time: float = 0.0
    latencies: collections.deque[float] = field(default_factory=lambda: collections.deque(maxlen=LATENCIES_KEPT))
    delivered_before: int = 0  # at the last status
    lock: threading.Lock = field(default_factory=threading.Lock)

    def error(self, text: str) -> None:
        with self.lock:
            self.errors += 1
            self.last_error, self.last_error_time = text, time.time()
        log.warning("%s", text)


def _quantile(ordered: list[float], q: float) -> float:
    if not ordered:
        return 0.0
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


class _Inbound:
    """One ROS -> WM mapping: the outbox the ROS callback fills, and the writer thread that empties it."""

    def __init__(self, bridge: RosBridge, mapping: RosToWm, converter: Converter) -> None:
        self.bridge = bridge
        self.mapping = mapping
        self.converter = converter
        self.stats = _Stats()
        self.cond = threading.Condition()
        self.queue: collections.deque[tuple[Any, float]] = collections.deque()
        self.min_gap = 1.0 / mapping.max_rate if mapping.max_rate > 0 else 0.0
        self.last_taken = 0.0
        self.written: collections.deque[str] = collections.deque()  # each: ids of our entries, oldest first
        self.exists = False  # latest: whether the entry is known to be there (overwrite, not add)
        self.in_flight = 0  # 1 while the writer holds a message taken from the queue
        self.thread = threading.Thread(target=self._run, name=f"ros-to-wm {mapping.topic}", daemon=True)

    @property
    def pending(self) -> int:
        return len(self.queue) + self.in_flight

    def on_message(self, ros_message: Any) -> None:
        now = time.time()
        with self.stats.lock:
            self.stats.received += 1
            self.stats.last_time = now
            if self.min_gap and now - self.last_taken < self.min_gap:
                self.stats.dropped += 1
                return
            self.last_taken = now
        with self.cond:
            if self.mapping.store == "latest":
                if self.queue:
                    self.queue.clear()
                    with self.stats.lock:
                        self.stats.dropped += 1
            elif len(self.queue) >= self.mapping.buffer:
                self.queue.popleft()
                with self.stats.lock:
                    self.stats.dropped += 1
            self.queue.append((ros_message, now))
            self.cond.notify()

    def seed(self) -> None:
        """Each: the entries an earlier run of this bridge left, so that ``keep`` bounds them too."""
        if self.mapping.store != "each":
            return
        prefix = self.mapping.entry_id + "/"
        try:
            entries = self.bridge.get_all(self.converter.proto_class, subarchitecture=self.mapping.subarchitecture)
        except cast.CastError as exc:
            log.warning("ROS bridge: cannot read the entries of %s: %s", self.mapping.topic, exc.message)
            return
        mine = sorted(e.id for e in entries if e.id.startswith(prefix) and e.author == self.bridge.component_id)
        self.written.extend(mine)

    def _run(self) -> None:
        while True:
            with self.cond:
                while not self.queue and self.bridge.running:
                    self.cond.wait(0.5)
                if not self.bridge.running:
                    return
                ros_message, received = self.queue.popleft()
                self.in_flight = 1
            try:
                value = self.converter.to_proto(ros_message)
            except ConversionError as exc:
                self.in_flight = 0
                self.stats.error(f"topic {self.mapping.topic}: {exc}")
                continue
            written = self._write(value, received)
            self.in_flight = 0
            if not written:
                continue  # stopped, refused (counted), or replaced by a newer message (latest)
            acked = time.time()
            stamp = _stamp_seconds(ros_message)
            with self.stats.lock:
                self.stats.delivered += 1
                self.stats.latencies.append(acked - (stamp if stamp > 0 else received))
            self._trim()

    def _write(self, value: message.Message, received: float) -> bool:
        """Write one message until the server acknowledges it; False when stopped, refused or replaced."""
        m, sa = self.mapping, self.mapping.subarchitecture
        entry_id = m.entry_id if m.store == "latest" else f"{m.entry_id}/{int(received * 1e9):019d}"
        while self.bridge.running:
            try:
                if m.store == "each":
                    try:
                        self.bridge.add(entry_id, value, subarchitecture=sa)
                    except cast.AlreadyExistsError:
                        pass  # a try the server applied before it went away
                    self.written.append(entry_id)
                elif self.exists:
                    try:
                        self.bridge.overwrite(entry_id, value, subarchitecture=sa)
                    except cast.NotFoundError:  # deleted by someone, or a server that lost its WMs
                        self.exists = False
                        continue
                else:
                    try:
                        self.bridge.add(entry_id, value, subarchitecture=sa)
                    except cast.AlreadyExistsError:
                        self.exists = True
                        continue
                    self.exists = True
                return True
            except (cast.UnavailableError, cast.DeadlineExceededError):
                self.bridge.wait_for_stop(RETRY_S)  # the server is away: the same message again, soon
                if m.store == "latest" and self.queue:
                    with self.stats.lock:
                        self.stats.dropped += 1  # a newer state arrived meanwhile: that one is written instead
                    return False
            except cast.CastError as exc:
                self.stats.error(f"topic {m.topic}: the server refused the write of {entry_id} into "
                                 f"'{sa}': {exc.message}")
                return False
        return False

    def _trim(self) -> None:
        """Each: delete the oldest of our entries past ``keep`` (a failed delete is tried after the next write)."""
        while len(self.written) > self.mapping.keep and self.bridge.running:
            oldest = self.written[0]
            try:
                self.bridge.delete_entry(oldest, subarchitecture=self.mapping.subarchitecture)
            except cast.NotFoundError:
                pass
            except cast.CastError:
                return
            self.written.popleft()

    def status(self, period: float) -> bridge_pb2.BridgeMapping:
        m = self.mapping
        entry = f"latest {m.entry_id}" if m.store == "latest" else f"each {m.entry_id}/<ns> (keep {m.keep})"
        out = _status(self.stats, period, "to_wm", m.topic, m.type, self.converter, m.subarchitecture, entry)
        out.pending = self.pending
        return out


class _Outbound:
    """One WM -> ROS mapping: a watch whose changes are converted and published."""

    def __init__(self, bridge: RosBridge, mapping: WmToRos, converter: Converter,
                 publish: Callable[[Any], None]) -> None:
        self.bridge = bridge
        self.mapping = mapping
        self.converter = converter
        self.publish = publish
        self.stats = _Stats()

    def start(self) -> None:
        w = self.mapping.watch
        ops = frozenset({cast.Operation.ADD, cast.Operation.OVERWRITE})
        watched = cast.ChangeFilter(ops, self.converter.proto_class.DESCRIPTOR.full_name, id=w.id,
                                    subarchitecture=w.subarchitecture, source_component=w.author, include_entry=True)
        self.bridge.on_change(watched, self.on_change)

    def on_change(self, change: cast.WorkingMemoryChange) -> None:
        if change.source_component == self.bridge.component_id:
            return  # the bridge's own write (of a to_wm mapping): never echoed back
        with self.stats.lock:
            self.stats.received += 1
            self.stats.last_time = time.time()
        try:
            value = change.entry(self.converter.proto_class).value
            ros_message = self.converter.to_ros(value)
        except ConversionError as exc:
            self.stats.error(f"topic {self.mapping.topic}: entry {change.id} of '{change.subarchitecture}': {exc}")
            return
        except cast.CastError as exc:
            self.stats.error(f"topic {self.mapping.topic}: entry {change.id}: {exc.message}")
            return
        try:
            self.publish(ros_message)
        except Exception as exc:  # noqa: BLE001 - the ROS library's own errors: counted, named, and the bridge goes on
            self.stats.error(f"topic {self.mapping.topic}: publishing entry {change.id} failed: {exc}")
            return
        with self.stats.lock:
            self.stats.delivered += 1

    def status(self, period: float) -> bridge_pb2.BridgeMapping:
        w = self.mapping.watch
        entry = f"id {w.id}" if w.id else f"author {w.author}" if w.author else "all"
        return _status(self.stats, period, "to_ros", self.mapping.topic, self.mapping.type, self.converter,
                       w.subarchitecture, entry)


def _status(stats: _Stats, period: float, direction: str, topic: str, ros_type: str, converter: Converter,
            sa: str, entry: str) -> bridge_pb2.BridgeMapping:
    with stats.lock:
        ordered = sorted(stats.latencies)
        out = bridge_pb2.BridgeMapping(
            direction=direction, topic=topic, ros_type=ros_type,
            entry_type=converter.proto_class.DESCRIPTOR.full_name, subarchitecture=sa, entry=entry,
            received=stats.received, delivered=stats.delivered, dropped=stats.dropped, errors=stats.errors,
            rate_hz=(stats.delivered - stats.delivered_before) / period if period > 0 else 0.0,
            last_error=stats.last_error, latency_count=len(ordered),
            latency_p50_seconds=_quantile(ordered, 0.5), latency_p99_seconds=_quantile(ordered, 0.99),
            latency_max_seconds=ordered[-1] if ordered else 0.0)
        stats.delivered_before = stats.delivered
        if stats.last_error_time:
            out.last_error_time.CopyFrom(_timestamp(stats.last_error_time))
        if stats.last_time:
            out.last_time.CopyFrom(_timestamp(stats.last_time))
    return out


class RosBridge(cast.UnmanagedComponent):
    """The ROS bridge (docs/ros.md); ``Ros2Bridge`` and ``Ros1Bridge`` give it its ROS side."""

    ros_version = 2

    def make_side(self, settings: RosBridgeConfig, node_name: str) -> RosSide:
        """The ROS side of this bridge's generation."""
        raise NotImplementedError

    def configure(self, args: dict[str, Any]) -> None:
        """Read the settings (``CAST_ROS_BRIDGE``) and every type the mappings use."""
        self.settings = settings_from(args)
        if self.settings.version != self.ros_version:
            raise cast.InvalidArgumentError(f"this is the ROS {self.ros_version} bridge; the settings are for ROS "
                                            f"{self.settings.version}")
        self.catalog = TypeCatalog(self.ros_version)
        # Every type is read now: a type this interpreter's ROS does not have stops the bridge before it starts.
        self.converters: dict[str, Converter] = {}
        mappings = [("to_wm", i, m.topic, m.type) for i, m in enumerate(self.settings.to_wm)] + \
                   [("to_ros", i, m.topic, m.type) for i, m in enumerate(self.settings.to_ros)]
        for direction, i, topic, type_name in mappings:
            try:
                if type_name not in self.converters:
                    self.converters[type_name] = Converter(self.catalog, type_name)
            except RosTypeError as exc:
                raise cast.InvalidArgumentError(f"ROS bridge {self.component_id}, {direction}[{i}] ({topic}): "
                                                f"{exc}") from None
        self.inbound: list[_Inbound] = []
        self.outbound: list[_Outbound] = []
        self.reconnections = 0
        self.side: RosSide | None = None
        self.status_id = f"{self.component_id}.status"

    def start(self) -> None:
        """Join ROS, subscribe and advertise every mapping, watch the WMs of the to_ros ones."""
        s = self.settings
        self.side = self.make_side(s, s.node or self.component_id.replace("-", "_").replace(".", "_"))
        for m in s.to_wm:
            inbound = _Inbound(self, m, self.converters[m.type])
            inbound.seed()
            self.inbound.append(inbound)
        for out in s.to_ros:
            converter = self.converters[out.type]
            publish = self.side.advertise(out.topic, self.catalog.ros_class(out.type), out.qos)
            outbound = _Outbound(self, out, converter, publish)
            outbound.start()
            self.outbound.append(outbound)
        for inbound in self.inbound:
            inbound.thread.start()
            self.side.subscribe(inbound.mapping.topic, self.catalog.ros_class(inbound.mapping.type),
                                inbound.mapping.qos, inbound.on_message)
        self.log.info("ROS bridge %s: %d topic(s) to WMs, %d to ROS", self.side.node_name, len(self.inbound),
                      len(self.outbound))

    def run(self) -> None:
        """Write the status entry every status period; ask the ROS side whether it had to register again."""
        period = self.settings.status_period
        last = time.monotonic()
        while not self.wait_for_stop(period):
            assert self.side is not None
            try:
                if self.side.poll():
                    self.reconnections += 1
            except Exception as exc:  # noqa: BLE001 - a ROS library's error must not end the bridge: said, tried again
                log.warning("ROS bridge: checking the ROS connection failed: %s", exc)
            now = time.monotonic()
            self._write_status(now - last)
            last = now

    def status(self, period: float) -> bridge_pb2.BridgeStatus:
        """The bridge's state now (``period``: seconds since the last status, for the rates)."""
        assert self.side is not None
        out = bridge_pb2.BridgeStatus(bridge=self.component_id, middleware=self.side.middleware,
                                      node=self.side.node_name, reconnections=self.reconnections)
        out.time.CopyFrom(_timestamp(time.time()))
        out.mappings.extend([i.status(period) for i in self.inbound] + [o.status(period) for o in self.outbound])
        return out

    def _write_status(self, period: float) -> None:
        try:
            self.overwrite(self.status_id, self.status(period))
        except cast.NotFoundError:
            try:
                self.add(self.status_id, self.status(period))
            except cast.CastError as exc:
                log.debug("status not written: %s", exc.message)
        except cast.CastError as exc:
            log.debug("status not written: %s", exc.message)

    def stop(self) -> None:
        """Leave ROS; the writer threads end."""
        if self.side is not None:
            self.side.close()
        for inbound in self.inbound:
            with inbound.cond:
                inbound.cond.notify_all()
        for inbound in self.inbound:
            inbound.thread.join(5)
