"""From a YAML tree to a :class:`SystemConfig`, reporting every problem with its line.

Two passes. The first checks the tree against the configuration's JSON Schema
(``system.schema.json``: keys, types, enums, names; :mod:`cast.config.schema_check`
reports each problem on its line and removes the wrong values). The second,
here, builds the model with the schema's defaults and checks what a schema
cannot say: references between keys (a component's SA exists, a server hosts
known SAs, ids are unique), rules that depend on another key's value (what
each ``language`` needs), and task managers, whose options their policy class
declares (:class:`cast.core.policies.PolicyOption`; a user's class is known
only once imported).

Components are written under their SA (``subarchitectures.vision.components``)
or in a top-level ``components:`` mapping with a ``subarchitecture:`` key each;
the second form lets a variable move a component to another SA, which is how
one file describes several decompositions of the same components.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from cast.config.commands import component_run
from cast.config.images import build_images
from cast.config.model import (
    LOCAL_HOST,
    AuthConfig,
    ComponentConfig,
    HostConfig,
    OrchestratorOptions,
    PersistenceConfig,
    RestartPolicy,
    ServerConfig,
    SubarchitectureConfig,
    SystemConfig,
    TlsConfig,
)
from cast.config.problems import Position, Problems, did_you_mean
from cast.config.ros import build_ros
from cast.config.schema import PY_CLASS_PATTERN, defaults, runtime_schema
from cast.config.schema_check import Path as KeyPath
from cast.config.schema_check import check_tree, dotted
from cast.config.source import SourceTree, YList, YMap
from cast.config.syspath import extended_sys_path
from cast.core.policies import BUILTIN_POLICIES, DEFAULT_POLICY, TaskPolicy, make_policy, policy_class
from cast.core.records import Limits, Quota
from cast.core.shared import SharedSettings
from cast.errors import InvalidArgumentError

__all__ = ["build_config"]

_PY_CLASS = re.compile(PY_CLASS_PATTERN)
_JAVA_CLASS = re.compile(r"[A-Za-z_$][\w$]*(\.[A-Za-z_$][\w$]*)*\Z")


def _get(m: YMap, key: str, default: dict[str, Any]) -> Any:
    """The value of ``key``, or the schema's default when it is not written (or written empty)."""
    value = m.get(key)
    return default[key] if value is None else value


class _Builder:
    def __init__(self, tree: SourceTree) -> None:
        self.root = tree.root
        self.p: Problems = tree.problems
        self.component_seen: dict[str, Position] = {}
        self.hosts: dict[str, HostConfig] = {}
        self.host_keys: set[str] = set()  # every name written under hosts:, valid or not (the wrong ones reported)
        self.server_host_at: dict[str, Position] = {}  # where each server on another host names its host
        self.invalid = check_tree(self.root, runtime_schema(), self.p)

    def written(self, path: KeyPath) -> bool:
        """Whether ``path`` was written, valid or not (a wrong value was reported and removed already)."""
        if path in self.invalid:
            return True
        node: Any = self.root
        for step in path:
            if not isinstance(node, YMap) or str(step) not in node:
                return False
            node = node[str(step)]
        return True

    # ------------------------------------------------------------- sections

    def build(self) -> SystemConfig:
        root = self.root
        top = defaults()
        name = str(_get(root, "system", top)) or str(top["system"])
        python_path = self.paths(root, "python_path")
        self.hosts = self.host_section()
        with extended_sys_path(python_path):  # user policy classes may live there
            sas = self.subarchitectures()
        self.placed_components(sas)
        if not sas and "subarchitectures" in root:
            self.p.error(root.at("subarchitectures"), "subarchitectures", "name at least one subarchitecture")
        elif not self.written(("subarchitectures",)):
            self.p.error(root.pos, "subarchitectures", "missing: name at least one subarchitecture")
        servers = self.servers(sas)
        persistence = self.persistence(root, ())
        if persistence is not None:
            if "servers" in root:
                self.p.error(root.at("persistence"), "persistence",
                             "with a 'servers:' section, give each server its own 'persistence:' (one file each)")
            else:
                servers[0].persistence = persistence
        self.reachable(sas, servers)
        return SystemConfig(
            name=name,
            subarchitectures=sas,
            limits=self.limits(),
            shared_memory=self.shared_memory(),
            source=str(root.pos.file),
            servers=servers,
            python_path=python_path,
            orchestrator=self.orchestrator(),
            tls=self.tls(),
            auth=self.auth(),
            hosts=self.hosts,
        )

    def subarchitectures(self) -> dict[str, SubarchitectureConfig]:
        out: dict[str, SubarchitectureConfig] = {}
        raw_sas = self.root.get("subarchitectures")
        for sa_name, raw in (raw_sas or {}).items():
            assert raw_sas is not None
            path: KeyPath = ("subarchitectures", sa_name)
            raw = raw if raw is not None else YMap(raw_sas.at(sa_name))  # `vision:` alone is an SA with defaults
            sa = SubarchitectureConfig(sa_name, position=raw_sas.at(sa_name))
            self.task_manager(sa, raw, path)
            out[sa_name] = sa
            comps = raw.get("components")
            for comp_id, craw in (comps or {}).items():
                assert comps is not None
                self.component(sa, comp_id, craw, comps.at(comp_id), (*path, "components", comp_id))
        return out

    def placed_components(self, sas: dict[str, SubarchitectureConfig]) -> None:
        """The top-level ``components:``, each into the SA its ``subarchitecture:`` names."""
        flat = self.root.get("components")
        for comp_id, raw in (flat or {}).items():
            assert flat is not None
            path: KeyPath = ("components", comp_id)
            if "subarchitecture" not in raw:  # missing (reported by the schema) or not a word
                continue
            sa_name = "" if raw["subarchitecture"] is None else str(raw["subarchitecture"])
            sa = sas.get(sa_name)
            if sa is None:
                self.p.error(raw.value_at("subarchitecture"), f"{dotted(path)}.subarchitecture",
                             f"unknown subarchitecture '{sa_name}'{did_you_mean(sa_name, sas)}")
                continue
            self.component(sa, comp_id, raw, flat.at(comp_id), path)

    # ------------------------------------------------------------ task managers

    def task_manager(self, sa: SubarchitectureConfig, raw: YMap, path: KeyPath) -> None:
        tm = raw.get("task_manager")
        if tm is None:
            return
        where = f"{dotted(path)}.task_manager"
        if "policy" not in tm and self.written((*path, "task_manager", "policy")):
            return  # a policy that is no word was reported; its options cannot be judged without it
        policy = DEFAULT_POLICY if tm.get("policy") is None else str(tm["policy"])
        try:
            cls = policy_class(policy)  # imports a user's module:Class
        except InvalidArgumentError as exc:
            message = exc.message
            if ":" not in policy:
                message = (f"unknown task manager policy '{policy}'{did_you_mean(policy, BUILTIN_POLICIES)}; "
                           "or name your own class as module:Class")
            self.p.error(tm.value_at("policy"), f"{where}.policy", message)
            return
        options = self.policy_options(cls, policy, tm, where)
        sa.policy, sa.policy_options = policy, options
        try:
            make_policy(policy, options)  # what only the constructor of a user's class knows
        except InvalidArgumentError as exc:
            self.p.error(tm.value_at("policy"), f"{where}.policy", exc.message)

    def policy_options(self, cls: type[TaskPolicy], policy: str, tm: YMap, where: str) -> dict[str, Any]:
        """The options of ``tm`` that its policy class declares, right; each other one reported on its line."""
        options = {k: v for k, v in tm.items() if k != "policy"}
        if cls.options is None:  # a class that declares nothing gets everything, as before declarations
            return options
        declared = {o.name: o for o in cls.options}
        valid: dict[str, Any] = {}
        for key, value in options.items():
            option = declared.get(key)
            if option is None:
                hint = did_you_mean(key, {*declared, "policy"})
                self.p.error(tm.at(key), f"{where}.{key}", f"unknown key '{key}'{hint}")
            elif (problem := option.problem(value)) is not None:
                self.p.error(tm.value_at(key), f"{where}.{key}", f"task manager policy '{policy}': {key} {problem}")
            else:
                valid[key] = value
        return valid

    # --------------------------------------------------------------- components

    def component(self, sa: SubarchitectureConfig, comp_id: str, raw: YMap, pos: Position, path: KeyPath) -> None:
        where = dotted(path)
        first = self.component_seen.get(comp_id)
        if first is not None:
            self.p.error(pos, where, f"component id '{comp_id}' is used twice (first at {first}): "
                                     "component ids are unique in a system")
            return
        self.component_seen[comp_id] = pos
        d = defaults("#component")
        language = str(_get(raw, "language", d))
        cls = "" if raw.get("class") is None else str(raw["class"])
        run, command = "", list[str]()  # a wrong run: was reported by the schema
        if not (self.written((*path, "run")) and "run" not in raw):
            run, command = component_run(raw, language, pos, where, self.p)
        in_process, manual = bool(_get(raw, "in_process", d)), bool(_get(raw, "manual", d))
        self.language_rules(raw, pos, path, language, cls, in_process, manual)
        args = raw.get("args")
        classpath = self.paths(raw, "classpath")
        host = self.host_name(raw, f"{where}.host")
        if host != LOCAL_HOST and in_process:
            self.p.error(raw.value_at("host"), f"{where}.host",
                         f"an in_process component runs inside its server, on the orchestrator's host: remove "
                         f"'host: {host}' or 'in_process: true'")
            host = LOCAL_HOST
        ros = None
        if language == "ros":
            if raw.get("ros") is None and not self.written((*path, "ros")):
                self.p.error(pos, f"{where}.ros", "a ROS bridge (language: ros) needs a 'ros:' section with its "
                                                  "mappings (docs/ros.md)")
            if str(_get(raw, "kind", d)) == "managed":
                self.p.error(raw.value_at("kind"), f"{where}.kind",
                             "the ROS bridge is unmanaged: remove 'kind: managed'")
            ros = build_ros(raw.get("ros"), f"{where}.ros", sa.name, bool(_get(raw, "privileged", d)),
                            set(self.root.get("subarchitectures") or {}), self.p)
        sa.components[comp_id] = ComponentConfig(
            id=comp_id,
            subarchitecture=sa.name,
            language=language,
            kind=str(_get(raw, "kind", d)),
            cls=cls,
            run=run,
            command=command,
            args=_plain(args) if args is not None else {},
            privileged=bool(_get(raw, "privileged", d)),
            in_process=in_process,
            manual=manual,
            restart=self.restart(raw),
            quota=self.quota(raw),
            classpath=[str(p) for p in classpath],
            host=host,
            ros=ros,
            base_dir=Path(raw.pos.file).resolve().parent,
            position=pos,
            positions=dict(raw.value_pos),
        )

    def language_rules(
        self, raw: YMap, pos: Position, path: KeyPath, language: str, cls: str, in_process: bool, manual: bool
    ) -> None:
        """What a component needs or may not have, by its language (a schema cannot tie one key to another's value)."""
        where = dotted(path)
        class_given = self.written((*path, "class"))
        if language == "python" and not _PY_CLASS.match(cls) and not (class_given and "class" not in raw):
            self.p.error(raw.value_at("class") if cls else pos, f"{where}.class",
                         f"a python component needs 'class: module:Class'{', not ' + repr(cls) if cls else ''}")
        if language == "java" and not _JAVA_CLASS.match(cls) and not (class_given and "class" not in raw):
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

    def quota(self, raw: YMap) -> Quota | None:
        value = raw.get("quota")
        if value is None:
            return None
        d = defaults("#component", "quota")
        return Quota(entries=int(_get(value, "entries", d)), bytes=int(_get(value, "bytes", d)))

    def restart(self, raw: YMap) -> RestartPolicy:
        d = defaults("#restart")
        mode = defaults("#component")["restart"]
        value = raw.get("restart")
        if isinstance(value, YMap):
            mode = _get(value, "policy", d)
        elif value is not None:
            mode = value
            value = YMap(raw.pos)
        else:
            value = YMap(raw.pos)
        return RestartPolicy(
            mode=str(mode),
            max_restarts=int(_get(value, "max_restarts", d)),
            backoff=float(_get(value, "backoff", d)),
            max_backoff=float(_get(value, "max_backoff", d)),
        )

    # ------------------------------------------------- paths, servers, settings

    def paths(self, m: YMap, key: str) -> list[Path]:
        value = m.get(key)
        if value is None:
            return []
        if isinstance(value, YList):
            items = list(zip(value, value.item_pos, strict=True))
        else:
            items = [(value, m.value_at(key))]
        # Relative paths are relative to the file they are written in (it may be an include).
        return [_relative_to(pos, str(item)) for item, pos in items]

    def servers(self, sas: dict[str, SubarchitectureConfig]) -> list[ServerConfig]:
        raw = self.root.get("servers")
        if raw is None:
            return [ServerConfig("main", defaults("#server")["listen"], list(sas))]
        out: list[ServerConfig] = []
        hosted: dict[str, str] = {}
        for name, sraw in raw.items():
            where = f"servers.{name}"
            listen = str(_get(sraw, "listen", defaults("#server")))
            server = ServerConfig(name, listen, persistence=self.persistence(sraw, ("servers", name)))
            server.advertise = "" if sraw.get("advertise") is None else str(sraw["advertise"])
            host = self.host_name(sraw, f"{where}.host")
            if host != LOCAL_HOST and not out:
                self.p.error(sraw.value_at("host"), f"{where}.host",
                             f"server '{name}' is the directory (the first server), which runs on the orchestrator's "
                             f"host for now: put a server without host: first, or remove 'host: {host}'")
            server.host = host
            if host != LOCAL_HOST:
                self.server_host_at[name] = sraw.value_at("host")
            names = sraw.get("subarchitectures")
            for sa, pos in zip(names or [], names.item_pos if names else [], strict=True):
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

    # ------------------------------------------------------------------ hosts

    def host_section(self) -> dict[str, HostConfig]:
        """The ``hosts:`` section: name -> agent address (and TLS files)."""
        raw = self.root.get("hosts")
        out: dict[str, HostConfig] = {}
        self.host_keys = set(raw or {})
        for name, value in (raw or {}).items():
            if name == LOCAL_HOST:
                assert raw is not None
                self.p.error(raw.at(name), f"hosts.{name}", "'local' is the orchestrator's own host (the default "
                                                            "of host:), not a name to give another host")
                continue
            if isinstance(value, YMap):
                if "agent" not in value:
                    continue  # reported by the schema
                tls = value.get("tls")
                files: dict[str, Path | None] = {"ca": None, "cert": None, "key": None}
                if isinstance(tls, YMap) and "ca" in tls:
                    for key in files:
                        if key in tls:
                            files[key] = _relative_to(tls.value_at(key), str(tls[key]))
                out[name] = HostConfig(name, str(value["agent"]), files["ca"], files["cert"], files["key"])
            elif value is not None:
                out[name] = HostConfig(name, str(value))
        return out

    def host_name(self, raw: YMap, where: str) -> str:
        """The ``host:`` of a component or server: local, or a name under ``hosts:`` (an unknown one reported)."""
        value = raw.get("host")
        name = LOCAL_HOST if value is None else str(value)
        if name == LOCAL_HOST or name in self.hosts:
            return name
        if name in self.host_keys:
            return LOCAL_HOST  # its entry under hosts: is wrong, and was reported there
        known = {LOCAL_HOST, *self.hosts}
        hint = did_you_mean(name, known)
        if not self.hosts:
            hint += "; name the machines of the system and their agents' addresses under 'hosts:'"
        self.p.error(raw.value_at("host"), where, f"unknown host '{name}'{hint}")
        return LOCAL_HOST

    def reachable(self, sas: dict[str, SubarchitectureConfig], servers: list[ServerConfig]) -> None:
        """A component on another host must be able to dial the directory and its SA's server."""
        if not servers:
            return
        for sa in sas.values():
            for comp in sa.components.values():
                if comp.host == LOCAL_HOST or comp.manual:
                    continue
                needed = [servers[0], *(s for s in servers[1:] if sa.name in s.subarchitectures)]
                for server in needed:
                    problem = _unreachable(server)
                    if problem:
                        role = "the directory" if server is servers[0] else f"the server of SA '{sa.name}'"
                        self.p.error(comp.at("host"), f"components.{comp.id}.host",
                                     f"'{comp.id}' runs on host '{comp.host}' but {role}, server '{server.name}', "
                                     f"{problem}: give server '{server.name}' an address other hosts reach "
                                     f"(listen: on this host's address, or advertise: HOST:PORT)")
        for i, far in enumerate(servers):
            if far.host == LOCAL_HOST:
                continue
            for later in servers[i + 1:]:
                # Remote servers start in the file's order, each told the others' addresses when it starts.
                if later.host != LOCAL_HOST and (later.advertise or later.listen).endswith(":0"):
                    self.p.error(self.server_host_at[far.name], f"servers.{far.name}.host",
                                 f"server '{far.name}' on host '{far.host}' starts before server '{later.name}' "
                                 f"(host '{later.host}') and must be told its address, but '{later.name}' picks "
                                 "its port when it starts (port 0): give it a fixed port in listen: or advertise:, "
                                 "or put it first")
            # A server on another host is dialled by every other (routes, the directory's forwarding) and
            # dials the directory (its start barrier) and the others' SAs: all of them must be reachable.
            for server in servers:
                problem = _unreachable(server)
                if problem:
                    whose = "it" if server is far else f"server '{server.name}'"
                    self.p.error(self.server_host_at[far.name], f"servers.{far.name}.host",
                                 f"server '{far.name}' runs on host '{far.host}' but {whose} {problem}: give "
                                 f"server '{server.name}' an address other hosts reach (listen: on its host's "
                                 "address, or advertise: HOST:PORT)")

    def persistence(self, parent: YMap, path: KeyPath) -> PersistenceConfig | None:
        raw = parent.get("persistence")
        if raw is None or "path" not in raw:  # not written, or its path missing (reported by the schema)
            return None
        durability = str(_get(raw, "durability", defaults("#persistence")))
        return PersistenceConfig(_relative_to(raw.value_at("path"), raw["path"]), durability)

    def tls(self) -> TlsConfig | None:
        raw = self.root.get("tls")
        if raw is None or not all(k in raw for k in ("ca", "cert", "key")):
            return None
        ca, cert, key = (_relative_to(raw.value_at(k), raw[k]) for k in ("ca", "cert", "key"))
        client_cert = client_key = None
        if "client_cert" in raw and "client_key" in raw:  # one without the other was reported by the schema
            client_cert = _relative_to(raw.value_at("client_cert"), raw["client_cert"])
            client_key = _relative_to(raw.value_at("client_key"), raw["client_key"])
        client_auth = bool(_get(raw, "client_auth", defaults("tls")))
        return TlsConfig(ca, cert, key, client_auth, client_cert, client_key)

    def auth(self) -> AuthConfig:
        raw = self.root.get("auth") or YMap(self.root.pos)
        d = defaults("auth")
        return AuthConfig(bool(_get(raw, "reads_require_token", d)), float(_get(raw, "token_ttl", d)))

    def limits(self) -> Limits:
        raw = self.root.get("limits") or YMap(self.root.pos)
        d = defaults("limits")
        return Limits(**{key: int(_get(raw, key, d)) for key in d})

    def shared_memory(self) -> SharedSettings:
        raw = self.root.get("shared_memory") or YMap(self.root.pos)
        d = defaults("shared_memory")
        return SharedSettings(bool(_get(raw, "enabled", d)),
                              **{key: int(_get(raw, key, d)) for key in d if key != "enabled"})

    def orchestrator(self) -> OrchestratorOptions:
        raw = self.root.get("orchestrator") or YMap(self.root.pos)
        d = defaults("orchestrator")
        return OrchestratorOptions(
            connect_timeout=float(_get(raw, "connect_timeout", d)),
            stop_timeout=float(_get(raw, "stop_timeout", d)),
            lease_ms=int(_get(raw, "lease_ms", d)),
        )


def _relative_to(pos: Position, value: str) -> Path:
    """``value`` as a path: absolute, or relative to the directory of the file it is written in."""
    path = Path(value)
    return path if path.is_absolute() else (Path(pos.file).resolve().parent / path).resolve()


_LOOPBACK = ("127.", "localhost", "::1", "[::1]")
_WILDCARD = ("0.0.0.0", "", "::", "[::]", "*")


def _unreachable(server: ServerConfig) -> str:
    """Why other hosts cannot dial ``server`` as configured ("" if they can, as far as the file says)."""
    if server.advertise:
        return ""
    host = server.listen.rpartition(":")[0]
    if host.startswith(_LOOPBACK):
        return f"listens on the loopback address {server.listen} and has no advertise:"
    if host in _WILDCARD:
        return f"listens on the wildcard address {server.listen} (not an address to dial) and has no advertise:"
    return ""


def _plain(value: Any) -> Any:
    """A YAML tree as plain dicts and lists (JSON-ready component args)."""
    if isinstance(value, YMap):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, YList):
        return [_plain(v) for v in value]
    return value


def build_config(tree: SourceTree) -> SystemConfig:
    """Validate a loaded tree; problems are added to ``tree.problems`` (the caller decides to raise).

    The wrong values are removed from ``tree`` on the way (the model gets their defaults).
    """
    config = _Builder(tree).build()
    config.variables = dict(tree.variables.used)
    config.files = list(tree.files)
    config.images = build_images(tree.root, config, tree.problems)  # ties images: to the components
    return config
