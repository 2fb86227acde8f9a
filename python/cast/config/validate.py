"""From a YAML tree to a :class:`SystemConfig`, reporting every problem with its line.

Components are written under their SA (``subarchitectures.vision.components``)
or in a top-level ``components:`` mapping with a ``subarchitecture:`` key each;
the second form lets a variable move a component to another SA, which is how
one file describes several decompositions of the same components.
"""

from __future__ import annotations

import re
from dataclasses import fields
from pathlib import Path
from typing import Any

from cast.config.commands import component_run
from cast.config.model import (
    DEFAULT_LISTEN,
    DURABILITY_MODES,
    KINDS,
    LANGUAGES,
    RESTART_MODES,
    AuthConfig,
    ComponentConfig,
    OrchestratorOptions,
    PersistenceConfig,
    RestartPolicy,
    ServerConfig,
    SubarchitectureConfig,
    SystemConfig,
    TlsConfig,
)
from cast.config.problems import Position, Problems, closest, did_you_mean
from cast.config.source import SourceTree, YList, YMap
from cast.config.syspath import extended_sys_path
from cast.core.policies import BUILTIN_POLICIES, make_policy
from cast.core.records import Limits, Quota
from cast.errors import InvalidArgumentError

__all__ = ["build_config"]

TOP_KEYS = {
    "system", "subarchitectures", "components", "servers", "limits", "python_path", "orchestrator", "persistence",
    "tls", "auth",
}
SA_KEYS = {"task_manager", "components"}
COMPONENT_KEYS = {
    "language", "kind", "class", "run", "args", "privileged", "in_process", "manual", "restart", "classpath",
    "quota",
}
QUOTA_KEYS = {"entries", "bytes"}
RESTART_KEYS = {"policy", "max_restarts", "backoff", "max_backoff"}
SERVER_KEYS = {"listen", "subarchitectures", "persistence"}
PERSISTENCE_KEYS = {"path", "durability"}
TLS_KEYS = {"ca", "cert", "key", "client_auth", "client_cert", "client_key"}
AUTH_KEYS = {"reads_require_token", "token_ttl"}
ORCHESTRATOR_KEYS = {"connect_timeout", "stop_timeout", "lease_ms"}
POLICY_OPTIONS = {"always": set(), "exclusive": set(), "fifo": {"max_concurrent", "max_waiting"},
                  "priority": {"max_concurrent", "max_waiting"}}
LIMIT_KEYS = {f.name for f in fields(Limits)}
_NAME = re.compile(r"[A-Za-z0-9_.\-]{1,128}\Z")
_PY_CLASS = re.compile(r"[A-Za-z_][\w.]*:[A-Za-z_]\w*\Z")
_JAVA_CLASS = re.compile(r"[A-Za-z_$][\w$]*(\.[A-Za-z_$][\w$]*)*\Z")


class _Validator:
    def __init__(self, tree: SourceTree) -> None:
        self.root = tree.root
        self.p: Problems = tree.problems
        self.component_seen: dict[str, Position] = {}

    # ------------------------------------------------------------ helpers

    def keys(self, m: YMap, allowed: set[str], where: str) -> None:
        for key in m:
            if key not in allowed:
                self.p.error(m.at(key), f"{where}{key}", f"unknown key '{key}'{did_you_mean(key, allowed)}")

    def mapping(self, parent: YMap, key: str, where: str) -> YMap | None:
        value = parent.get(key)
        if value is None:
            return None
        if not isinstance(value, YMap):
            self.p.error(parent.value_at(key), where, f"must be a mapping, not {_kind(value)}")
            return None
        return value

    def string(self, m: YMap, key: str, where: str, default: str = "") -> str:
        value = m.get(key, default)
        if value is None:
            return default
        if isinstance(value, (YMap, YList)) or isinstance(value, bool):
            self.p.error(m.value_at(key), where, f"must be a word or text, not {_kind(value)}")
            return default
        return str(value)

    def boolean(self, m: YMap, key: str, where: str) -> bool:
        value = m.get(key, False)
        if not isinstance(value, bool):
            self.p.error(m.value_at(key), where, f"must be true or false, not {value!r}")
            return False
        return value

    def number(self, m: YMap, key: str, where: str, default: float, whole: bool = False) -> float:
        value = m.get(key, default)
        ok = isinstance(value, int) if whole else isinstance(value, (int, float))
        if not ok or isinstance(value, bool) or value < 0:
            kind = "a whole number" if whole else "a number"
            self.p.error(m.value_at(key), where, f"must be {kind} >= 0, not {value!r}")
            return default
        return float(value)

    def choice(self, m: YMap, key: str, where: str, allowed: tuple[str, ...], default: str) -> str:
        value = self.string(m, key, where, default)
        if value not in allowed:
            hint = closest(value, allowed)
            self.p.error(m.value_at(key), where, f"'{value}' is not one of {', '.join(allowed)}{hint}")
            return default
        return value

    def name(self, value: str, pos: Position, where: str, what: str) -> bool:
        if not _NAME.match(value):
            self.p.error(pos, where, f"{what} '{value}' must be 1 to 128 letters, digits, '_', '-' or '.'")
            return False
        return True

    # ------------------------------------------------------------- sections

    def build(self) -> SystemConfig:
        root = self.root
        self.keys(root, TOP_KEYS, "")
        name = self.string(root, "system", "system", "cast") or "cast"
        python_path = self.python_path()
        with extended_sys_path(python_path):  # user policy classes may live there
            sas = self.subarchitectures()
        flat = self.mapping(root, "components", "components")
        if flat is not None:
            for comp_id, raw in flat.items():
                where = f"components.{comp_id}"
                if not isinstance(raw, YMap):
                    self.p.error(flat.value_at(comp_id), where, f"must be a mapping, not {_kind(raw)}")
                    continue
                if "subarchitecture" not in raw:
                    self.p.error(flat.at(comp_id), where, "needs 'subarchitecture:' (the SA it belongs to)")
                    continue
                sa_name = self.string(raw, "subarchitecture", f"{where}.subarchitecture")
                sa = sas.get(sa_name)
                if sa is None:
                    self.p.error(raw.value_at("subarchitecture"), f"{where}.subarchitecture",
                                 f"unknown subarchitecture '{sa_name}'{did_you_mean(sa_name, sas)}")
                    continue
                self.component(sa, comp_id, raw, flat.at(comp_id), where, {"subarchitecture"})
        if not sas and "subarchitectures" in root:
            self.p.error(root.at("subarchitectures"), "subarchitectures", "name at least one subarchitecture")
        elif "subarchitectures" not in root:
            self.p.error(root.pos, "subarchitectures", "missing: name at least one subarchitecture")
        servers = self.servers(sas)
        persistence = self.persistence(root, "persistence")
        if persistence is not None:
            if "servers" in root:
                self.p.error(root.at("persistence"), "persistence",
                             "with a 'servers:' section, give each server its own 'persistence:' (one file each)")
            else:
                servers[0].persistence = persistence
        return SystemConfig(
            name=name,
            subarchitectures=sas,
            limits=self.limits(),
            source=str(root.pos.file),
            servers=servers,
            python_path=python_path,
            orchestrator=self.orchestrator(),
            tls=self.tls(),
            auth=self.auth(),
        )

    # ------------------------------------------------- reliability, security

    def one_path(self, m: YMap, key: str, where: str) -> Path | None:
        value = m.get(key)
        if not isinstance(value, str) or not value:
            self.p.error(m.value_at(key) if key in m else m.pos, where, "needs a file path")
            return None
        path = Path(value)
        # Relative paths are relative to the file they are written in, like python_path.
        return path if path.is_absolute() else (Path(m.value_at(key).file).resolve().parent / path).resolve()

    def persistence(self, parent: YMap, where: str) -> PersistenceConfig | None:
        raw = self.mapping(parent, "persistence", where)
        if raw is None:
            return None
        self.keys(raw, PERSISTENCE_KEYS, f"{where}.")
        path = self.one_path(raw, "path", f"{where}.path")
        durability = self.choice(raw, "durability", f"{where}.durability", DURABILITY_MODES, "batch")
        return None if path is None else PersistenceConfig(path, durability)

    def tls(self) -> TlsConfig | None:
        raw = self.mapping(self.root, "tls", "tls")
        if raw is None:
            return None
        self.keys(raw, TLS_KEYS, "tls.")
        ca, cert, key = (self.one_path(raw, k, f"tls.{k}") for k in ("ca", "cert", "key"))
        client_auth = self.boolean(raw, "client_auth", "tls.client_auth")
        client_cert = client_key = None
        if "client_cert" in raw or "client_key" in raw:
            if "client_cert" not in raw or "client_key" not in raw:
                missing = "client_key" if "client_cert" in raw else "client_cert"
                self.p.error(raw.pos, f"tls.{missing}", "give client_cert and client_key together, or neither")
            else:
                client_cert = self.one_path(raw, "client_cert", "tls.client_cert")
                client_key = self.one_path(raw, "client_key", "tls.client_key")
        if ca is None or cert is None or key is None:
            return None
        return TlsConfig(ca, cert, key, client_auth, client_cert, client_key)

    def auth(self) -> AuthConfig:
        raw = self.mapping(self.root, "auth", "auth")
        default = AuthConfig()
        if raw is None:
            return default
        self.keys(raw, AUTH_KEYS, "auth.")
        reads = raw.get("reads_require_token", True)
        if not isinstance(reads, bool):
            self.p.error(raw.value_at("reads_require_token"), "auth.reads_require_token",
                         f"must be true or false, not {reads!r}")
            reads = True
        return AuthConfig(reads, self.number(raw, "token_ttl", "auth.token_ttl", default.token_ttl))

    def subarchitectures(self) -> dict[str, SubarchitectureConfig]:
        out: dict[str, SubarchitectureConfig] = {}
        raw_sas = self.mapping(self.root, "subarchitectures", "subarchitectures")
        if raw_sas is None:
            return out
        for sa_name, raw in raw_sas.items():
            where = f"subarchitectures.{sa_name}"
            if not self.name(sa_name, raw_sas.at(sa_name), where, "subarchitecture name"):
                continue
            if raw is None:
                raw = YMap(raw_sas.at(sa_name))
            if not isinstance(raw, YMap):
                self.p.error(raw_sas.value_at(sa_name), where, f"must be a mapping, not {_kind(raw)}")
                continue
            self.keys(raw, SA_KEYS, f"{where}.")
            sa = SubarchitectureConfig(sa_name, position=raw_sas.at(sa_name))
            self.task_manager(sa, raw, where)
            out[sa_name] = sa
            comps = self.mapping(raw, "components", f"{where}.components")
            for comp_id, craw in (comps or {}).items():
                assert comps is not None
                cwhere = f"{where}.components.{comp_id}"
                if not isinstance(craw, YMap):
                    self.p.error(comps.value_at(comp_id), cwhere, f"must be a mapping, not {_kind(craw)}")
                    continue
                self.component(sa, comp_id, craw, comps.at(comp_id), cwhere, set())
        return out

    def task_manager(self, sa: SubarchitectureConfig, raw: YMap, where: str) -> None:
        tm = self.mapping(raw, "task_manager", f"{where}.task_manager")
        if tm is None:
            return
        twhere = f"{where}.task_manager"
        policy = self.string(tm, "policy", f"{twhere}.policy", "always")
        options = {k: v for k, v in tm.items() if k != "policy"}
        if policy in POLICY_OPTIONS:
            self.keys(YMapView(tm, set(options)), POLICY_OPTIONS[policy] | {"policy"}, f"{twhere}.")
            options = {k: v for k, v in options.items() if k in POLICY_OPTIONS[policy]}
        elif ":" not in policy:
            self.p.error(tm.value_at("policy"), f"{twhere}.policy",
                         f"unknown task manager policy '{policy}'{did_you_mean(policy, BUILTIN_POLICIES)}; "
                         "or name your own class as module:Class")
            return
        sa.policy, sa.policy_options = policy, options
        try:
            make_policy(policy, options)
        except InvalidArgumentError as exc:
            self.p.error(tm.value_at("policy"), f"{twhere}.policy", exc.message)

    def component(
        self, sa: SubarchitectureConfig, comp_id: str, raw: YMap, pos: Position, where: str, extra: set[str]
    ) -> None:
        if not self.name(comp_id, pos, where, "component id"):
            return
        self.keys(raw, COMPONENT_KEYS | extra, f"{where}.")
        first = self.component_seen.get(comp_id)
        if first is not None:
            self.p.error(pos, where, f"component id '{comp_id}' is used twice (first at {first}): "
                                     "component ids are unique in a system")
            return
        self.component_seen[comp_id] = pos
        language = self.choice(raw, "language", f"{where}.language", LANGUAGES, "python")
        kind = self.choice(raw, "kind", f"{where}.kind", KINDS, "unmanaged")
        cls = self.string(raw, "class", f"{where}.class")
        run, command = component_run(raw, language, pos, where, self.p)
        args = self.mapping(raw, "args", f"{where}.args")
        in_process = self.boolean(raw, "in_process", f"{where}.in_process")
        manual = self.boolean(raw, "manual", f"{where}.manual")
        if language == "python" and not _PY_CLASS.match(cls):
            self.p.error(raw.value_at("class") if cls else pos, f"{where}.class",
                         f"a python component needs 'class: module:Class'{', not ' + repr(cls) if cls else ''}")
        if language == "java" and not _JAVA_CLASS.match(cls):
            not_this = f", not {cls!r}" if cls else ""
            self.p.error(raw.value_at("class") if cls else pos, f"{where}.class",
                         f"a java component needs 'class: fully.qualified.ClassName'{not_this}")
        if in_process and language != "python":
            self.p.error(raw.at("in_process"), f"{where}.in_process",
                         f"only python components can run in process; one of language {language} is its own "
                         f"process ({'its run: command' if language == 'other' else 'started by cast run'}): "
                         "remove 'in_process: true'")
        if in_process and manual:
            self.p.error(raw.at("manual"), f"{where}.manual", "a component is either in_process or manual, not both")
        base_dir = Path(raw.pos.file).resolve().parent
        classpath = self.paths(raw, "classpath", f"{where}.classpath")
        sa.components[comp_id] = ComponentConfig(
            id=comp_id,
            subarchitecture=sa.name,
            language=language,
            kind=kind,
            cls=cls,
            run=run,
            command=command,
            args=_plain(args) if args is not None else {},
            privileged=self.boolean(raw, "privileged", f"{where}.privileged"),
            in_process=in_process,
            manual=manual,
            restart=self.restart(raw, where),
            quota=self.quota(raw, where),
            classpath=[str(p) for p in classpath],
            base_dir=base_dir,
            position=pos,
            positions=dict(raw.value_pos),
        )

    def quota(self, raw: YMap, where: str) -> Quota | None:
        value = self.mapping(raw, "quota", f"{where}.quota")
        if value is None:
            return None
        self.keys(value, QUOTA_KEYS, f"{where}.quota.")
        return Quota(
            entries=int(self.number(value, "entries", f"{where}.quota.entries", 0, True)),
            bytes=int(self.number(value, "bytes", f"{where}.quota.bytes", 0, True)),
        )

    def restart(self, raw: YMap, where: str) -> RestartPolicy:
        value = raw.get("restart")
        rwhere = f"{where}.restart"
        if value is None:
            return RestartPolicy()
        if isinstance(value, str):
            return RestartPolicy(mode=self.choice(raw, "restart", rwhere, RESTART_MODES, "on-failure"))
        if not isinstance(value, YMap):
            self.p.error(raw.value_at("restart"), rwhere, "must be never, on-failure, always, or a mapping "
                                                           "{policy:, max_restarts:, backoff:}")
            return RestartPolicy()
        self.keys(value, RESTART_KEYS, f"{rwhere}.")
        default = RestartPolicy()
        return RestartPolicy(
            mode=self.choice(value, "policy", f"{rwhere}.policy", RESTART_MODES, default.mode),
            max_restarts=int(
                self.number(value, "max_restarts", f"{rwhere}.max_restarts", default.max_restarts, True)
            ),
            backoff=self.number(value, "backoff", f"{rwhere}.backoff", default.backoff),
            max_backoff=self.number(value, "max_backoff", f"{rwhere}.max_backoff", default.max_backoff),
        )

    def paths(self, m: YMap, key: str, where: str) -> list[Path]:
        value = m.get(key)
        if value is None:
            return []
        if isinstance(value, YList):
            items = list(zip(value, value.item_pos, strict=True))
        else:
            items = [(value, m.value_at(key))]
        out = []
        for item, pos in items:
            if not isinstance(item, str) or not item:
                self.p.error(pos, where, "must be a path or a list of paths")
                continue
            path = Path(item)
            # Relative paths are relative to the file they are written in (it may be an include).
            out.append(path if path.is_absolute() else (Path(pos.file).resolve().parent / path).resolve())
        return out

    def python_path(self) -> list[Path]:
        out = self.paths(self.root, "python_path", "python_path")
        return out

    def servers(self, sas: dict[str, SubarchitectureConfig]) -> list[ServerConfig]:
        raw = self.mapping(self.root, "servers", "servers")
        if raw is None:
            return [ServerConfig("main", DEFAULT_LISTEN, list(sas))]
        out: list[ServerConfig] = []
        hosted: dict[str, str] = {}
        for name, sraw in raw.items():
            where = f"servers.{name}"
            if not isinstance(sraw, YMap):
                self.p.error(raw.value_at(name), where, f"must be a mapping, not {_kind(sraw)}")
                continue
            self.keys(sraw, SERVER_KEYS, f"{where}.")
            listen = self.string(sraw, "listen", f"{where}.listen", DEFAULT_LISTEN)
            _, sep, port = listen.rpartition(":")
            if not sep or not port.isdigit() or int(port) > 65535:
                self.p.error(sraw.value_at("listen"), f"{where}.listen",
                             f"'{listen}' must be HOST:PORT (port 0 picks a free port)")
            names = sraw.get("subarchitectures")
            server = ServerConfig(name, listen, persistence=self.persistence(sraw, f"{where}.persistence"))
            if not isinstance(names, YList) or not names:
                self.p.error(sraw.at("subarchitectures") if names is not None else raw.at(name),
                             f"{where}.subarchitectures", "list the SAs this server hosts, e.g. [vision, language]")
            else:
                for sa, pos in zip(names, names.item_pos, strict=True):
                    sa = str(sa)
                    if sa not in sas:
                        self.p.error(pos, f"{where}.subarchitectures",
                                     f"unknown subarchitecture '{sa}'{did_you_mean(sa, sas)}")
                    elif sa in hosted:
                        self.p.error(pos, f"{where}.subarchitectures",
                                     f"subarchitecture '{sa}' is already hosted by server '{hosted[sa]}'")
                    else:
                        hosted[sa] = name
                        server.subarchitectures.append(sa)
            out.append(server)
        for sa in sas:
            if sa not in hosted and out:
                self.p.error(self.root.at("servers"), "servers",
                             f"no server hosts subarchitecture '{sa}': add it to one server's subarchitectures")
        return out

    def limits(self) -> Limits:
        raw = self.mapping(self.root, "limits", "limits")
        if raw is None:
            return Limits()
        self.keys(raw, LIMIT_KEYS, "limits.")
        values: dict[str, int] = {}
        for key, value in raw.items():
            if key not in LIMIT_KEYS:
                continue
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                self.p.error(raw.value_at(key), f"limits.{key}", f"must be a positive whole number, not {value!r}")
            else:
                values[key] = value
        return Limits(**values)

    def orchestrator(self) -> OrchestratorOptions:
        raw = self.mapping(self.root, "orchestrator", "orchestrator")
        default = OrchestratorOptions()
        if raw is None:
            return default
        self.keys(raw, ORCHESTRATOR_KEYS, "orchestrator.")
        return OrchestratorOptions(
            connect_timeout=self.number(
                raw, "connect_timeout", "orchestrator.connect_timeout", default.connect_timeout
            ),
            stop_timeout=self.number(raw, "stop_timeout", "orchestrator.stop_timeout", default.stop_timeout),
            lease_ms=int(self.number(raw, "lease_ms", "orchestrator.lease_ms", default.lease_ms, True)),
        )


class YMapView(YMap):
    """The keys of a mapping restricted to ``names`` (to check option names with positions)."""

    def __init__(self, src: YMap, names: set[str]) -> None:
        super().__init__(src.pos)
        for name in names:
            self[name] = src[name]
            self.key_pos[name] = src.at(name)


def _kind(value: Any) -> str:
    if isinstance(value, YMap):
        return "a mapping"
    if isinstance(value, YList):
        return "a list"
    if value is None:
        return "empty"
    return f"{type(value).__name__} {value!r}"


def _plain(value: Any) -> Any:
    """A YAML tree as plain dicts and lists (JSON-ready component args)."""
    if isinstance(value, YMap):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, YList):
        return [_plain(v) for v in value]
    return value


def build_config(tree: SourceTree) -> SystemConfig:
    """Validate a loaded tree; problems are added to ``tree.problems`` (the caller decides to raise)."""
    config = _Validator(tree).build()
    config.variables = dict(tree.variables.used)
    config.files = list(tree.files)
    return config
