"""The ``ros:`` section of a ROS bridge component (``language: ros``): its model, and its check on its lines.

The JSON Schema (``system.schema.json``, ``definitions.ros_*``) checks keys,
types and enums first; here are the rules a schema cannot say: type names
in the form of their ROS generation, topics that are ROS names, a target SA
that exists and that the bridge may write, a watch type that is the ROS
type's entry type, no two mappings writing one entry. The bridge (in another
interpreter) reads the same model back from ``CAST_ROS_BRIDGE`` (JSON), which
the launcher sets (docs/ros.md, "The bridge in the configuration").
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass
from typing import Any

from cast.config.problems import Problems, did_you_mean
from cast.config.source import YList, YMap

__all__ = ["QOS_DEFAULT", "RosBridgeConfig", "RosQos", "RosToWm", "RosWatch", "WmToRos", "build_ros",
           "proto_entry_type", "ros_type_problem"]

ROS_VERSIONS = (1, 2)
STORES = ("latest", "each")
_ROS2_TYPE = re.compile(r"[A-Za-z][A-Za-z0-9_]*/msg/[A-Za-z][A-Za-z0-9_]*\Z")
_ROS1_TYPE = re.compile(r"[A-Za-z][A-Za-z0-9_]*/[A-Za-z][A-Za-z0-9_]*\Z")
# A ROS graph name (global or relative; ~ private names are the node's: not for a bridge's topics).
_TOPIC = re.compile(r"/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*\Z")


@dataclass(frozen=True)
class RosQos:
    """The quality of service of a subscription or publication (ROS 2 terms; ROS 1 uses depth and durability)."""

    reliability: str = "reliable"  # reliable | best_effort
    durability: str = "volatile"  # volatile | transient_local (ROS 1: a latched publisher)
    history: str = "keep_last"  # keep_last | keep_all
    depth: int = 10  # keep_last's depth; ROS 1: the queue size


QOS_DEFAULT = RosQos()


@dataclass(frozen=True)
class RosToWm:
    """A ROS topic written into a WM: each message one overwrite of ``id`` (latest) or a new entry (each)."""

    topic: str
    type: str
    subarchitecture: str = ""  # "": the bridge's own SA
    store: str = "latest"
    id: str = ""  # latest: the entry id; each: the prefix of the ids (<id>/<receive time, ns>); "": the topic
    keep: int = 100  # each: how many entries stay (the oldest are deleted)
    max_rate: float = 0.0  # messages per second written at most (0: every one)
    buffer: int = 1000  # each: messages held while the server is away (then the oldest are dropped, and counted)
    qos: RosQos = QOS_DEFAULT

    @property
    def entry_id(self) -> str:
        """The entry id (latest) or id prefix (each): ``id``, else the topic without its leading ``/``."""
        return self.id or self.topic.lstrip("/")


@dataclass(frozen=True)
class RosWatch:
    """Which WM changes a WM -> ROS mapping publishes: its SA, and optionally one id or one author."""

    subarchitecture: str
    type: str = ""  # "": the ROS type's entry type (the only one that may be given)
    id: str = ""
    author: str = ""


@dataclass(frozen=True)
class WmToRos:
    """Entries of a WM published to a ROS topic, each add and overwrite one message."""

    watch: RosWatch
    topic: str
    type: str
    qos: RosQos = QOS_DEFAULT


@dataclass(frozen=True)
class RosBridgeConfig:
    """A ROS bridge: its ROS generation, interpreter, node, and its mappings both ways."""

    version: int = 2
    python: str = ""  # "": $CAST_ROS2_PYTHON / the orchestrator's own (2); $CAST_ROS1_PYTHON / /usr/bin/python3 (1)
    node: str = ""  # "": the component id
    namespace: str = ""
    status_period: float = 1.0
    to_wm: tuple[RosToWm, ...] = ()
    to_ros: tuple[WmToRos, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """A plain mapping (for JSON), read back by :meth:`from_dict`."""
        return asdict(self)

    @staticmethod
    def from_dict(data: dict[str, Any]) -> RosBridgeConfig:
        """The model of a mapping :meth:`to_dict` made."""
        to_wm = tuple(RosToWm(**{**m, "qos": RosQos(**m.get("qos", {}))}) for m in data.get("to_wm", ()))
        to_ros = tuple(WmToRos(watch=RosWatch(**m["watch"]), topic=m["topic"], type=m["type"],
                               qos=RosQos(**m.get("qos", {}))) for m in data.get("to_ros", ()))
        rest = {k: v for k, v in data.items() if k not in ("to_wm", "to_ros")}
        return RosBridgeConfig(**rest, to_wm=to_wm, to_ros=to_ros)


def ros_type_problem(name: str, version: int) -> str | None:
    """What is wrong with a ROS type name for its generation, or None."""
    if version == 2 and not _ROS2_TYPE.match(name):
        hint = ""
        if _ROS1_TYPE.match(name):
            package, type_name = name.split("/")
            hint = f" ({package}/msg/{type_name}?)"
        return f"'{name}' is not a ROS 2 message type: write package/msg/Name{hint}"
    if version == 1 and not _ROS1_TYPE.match(name):
        hint = ""
        if _ROS2_TYPE.match(name):
            package, _, type_name = name.split("/")
            hint = f" ({package}/{type_name}?)"
        return f"'{name}' is not a ROS 1 message type: write package/Name{hint}"
    return None


def proto_entry_type(name: str, version: int) -> str:
    """The entry type of a ROS type, by the bridge's naming scheme (cast.bridges.ros.model.proto_name)."""
    parts = name.split("/")
    return f"ros{version}.{parts[0]}.msg.{parts[-1]}"


def _qos(raw: Any) -> RosQos:
    if not isinstance(raw, YMap):
        return QOS_DEFAULT
    d = QOS_DEFAULT
    return RosQos(str(raw.get("reliability") or d.reliability), str(raw.get("durability") or d.durability),
                  str(raw.get("history") or d.history), int(raw["depth"]) if raw.get("depth") is not None else d.depth)


def _text(m: YMap, key: str, default: str = "") -> str:
    value = m.get(key)
    return default if value is None else str(value)


def build_ros(raw: Any, where: str, component_sa: str, privileged: bool, sas: set[str], p: Problems,
              ) -> RosBridgeConfig:
    """The bridge's model from its ``ros:`` mapping (checked by the schema already); problems on their lines.

    ``sas`` are the system's SAs; ``component_sa`` and ``privileged`` are the
    bridge's, which decide where it may write.
    """
    if not isinstance(raw, YMap):
        return RosBridgeConfig()
    version = int(raw["version"]) if raw.get("version") in ROS_VERSIONS else 2
    to_wm: list[RosToWm] = []
    targets: dict[tuple[str, str, str], str] = {}
    for i, (m, pos) in enumerate(_items(raw, "to_wm")):
        here = f"{where}.to_wm[{i}]"
        if not isinstance(m, YMap) or "topic" not in m or "type" not in m:
            continue  # reported by the schema
        mapping = RosToWm(
            topic=_text(m, "topic"), type=_text(m, "type"), subarchitecture=_text(m, "subarchitecture", component_sa),
            store=_text(m, "store", "latest"), id=_text(m, "id"),
            keep=int(m["keep"]) if m.get("keep") is not None else 100,
            max_rate=float(m["max_rate"]) if m.get("max_rate") is not None else 0.0,
            buffer=int(m["buffer"]) if m.get("buffer") is not None else 1000, qos=_qos(m.get("qos")))
        _topic(m, here, p)
        _type(m, here, version, p)
        if mapping.subarchitecture not in sas:
            p.error(m.value_at("subarchitecture"), f"{here}.subarchitecture",
                    f"unknown subarchitecture '{mapping.subarchitecture}'{did_you_mean(mapping.subarchitecture, sas)}")
        elif mapping.subarchitecture != component_sa and not privileged:
            p.error(m.value_at("subarchitecture"), f"{here}.subarchitecture",
                    f"the bridge belongs to '{component_sa}' and may write only there: make it 'privileged: true' to "
                    f"write into '{mapping.subarchitecture}', or put it in that SA")
        if mapping.store == "latest" and "keep" in m:
            p.error(m.at("keep"), f"{here}.keep", "keep bounds the entries of 'store: each'; 'store: latest' "
                                                  "overwrites one entry: remove keep, or write 'store: each'")
        if mapping.store == "latest" and "buffer" in m:
            p.error(m.at("buffer"), f"{here}.buffer", "buffer holds the messages of 'store: each' while the server is "
                                                      "away; 'store: latest' holds only the newest: remove buffer")
        key = (mapping.subarchitecture, mapping.store, mapping.entry_id)
        if key in targets:
            p.error(pos, here, f"writes the same entries as {targets[key]} ({mapping.store} '{mapping.entry_id}' in "
                               f"'{mapping.subarchitecture}'): give one of them another id")
        else:
            targets[key] = f"to_wm[{i}]"
        to_wm.append(mapping)
    to_ros: list[WmToRos] = []
    for i, (m, _) in enumerate(_items(raw, "to_ros")):
        here = f"{where}.to_ros[{i}]"
        if not isinstance(m, YMap) or not isinstance(m.get("watch"), YMap) or "topic" not in m or "type" not in m:
            continue  # reported by the schema
        w = m["watch"]
        watch = RosWatch(_text(w, "subarchitecture"), _text(w, "type"), _text(w, "id"), _text(w, "author"))
        _topic(m, here, p)
        type_ok = _type(m, here, version, p)
        if watch.subarchitecture not in sas:
            p.error(w.value_at("subarchitecture"), f"{here}.watch.subarchitecture",
                    f"unknown subarchitecture '{watch.subarchitecture}'{did_you_mean(watch.subarchitecture, sas)}")
        if type_ok and watch.type and watch.type != proto_entry_type(_text(m, "type"), version):
            p.error(w.value_at("type"), f"{here}.watch.type",
                    f"the bridge publishes entries of the ROS type's own entry type "
                    f"'{proto_entry_type(_text(m, 'type'), version)}', not '{watch.type}': write that, or leave "
                    f"type: out (a component converts other types into it: docs/ros.md)")
        if watch.id and watch.author:
            p.error(w.at("author"), f"{here}.watch.author", "watch one entry (id) or one author's entries, not both")
        to_ros.append(WmToRos(watch, _text(m, "topic"), _text(m, "type"), _qos(m.get("qos"))))
    if not to_wm and not to_ros:
        p.error(raw.pos, f"{where}", "a bridge with no mappings: give to_wm: or to_ros: (or both)")
    return RosBridgeConfig(
        version=version, python=_text(raw, "python"), node=_text(raw, "node"), namespace=_text(raw, "namespace"),
        status_period=float(raw["status_period"]) if raw.get("status_period") is not None else 1.0,
        to_wm=tuple(to_wm), to_ros=tuple(to_ros))


def _items(raw: YMap, key: str) -> list[tuple[Any, Any]]:
    value = raw.get(key)
    if not isinstance(value, YList):
        return []
    return list(zip(value, value.item_pos, strict=True))


def _topic(m: YMap, here: str, p: Problems) -> None:
    topic = _text(m, "topic")
    if not _TOPIC.match(topic):
        p.error(m.value_at("topic"), f"{here}.topic",
                f"'{topic}' is not a ROS topic name: names of letters, digits and _ separated by /, each starting "
                f"with a letter (/camera/image_raw)")


def _type(m: YMap, here: str, version: int, p: Problems) -> bool:
    problem = ros_type_problem(_text(m, "type"), version)
    if problem is not None:
        p.error(m.value_at("type"), f"{here}.type", problem + f" (this bridge speaks ROS {version})")
        return False
    return True

