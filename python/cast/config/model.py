"""The validated configuration: what the orchestrator and the server are given."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cast.config.problems import Position
from cast.config.ros import RosBridgeConfig
from cast.core.policies import TaskPolicy, make_policy
from cast.core.records import Limits, Quota
from cast.core.shared import SharedSettings

__all__ = [
    "DURABILITY_MODES",
    "LANGUAGES",
    "KINDS",
    "LOCAL_HOST",
    "RESTART_MODES",
    "AuthConfig",
    "ComponentConfig",
    "HostConfig",
    "ImagesConfig",
    "OrchestratorOptions",
    "PersistenceConfig",
    "RestartPolicy",
    "ServerConfig",
    "SubarchitectureConfig",
    "SystemConfig",
    "TlsConfig",
]

LANGUAGES = ("python", "cpp", "java", "other", "ros")  # other: any program speaking the gRPC API, started by run:;
# ros: the ROS bridge (cast.bridges.ros), configured by its ros: section
KINDS = ("unmanaged", "managed")
RESTART_MODES = ("never", "on-failure", "always")
DURABILITY_MODES = ("always", "batch", "none")
DEFAULT_LISTEN = "127.0.0.1:0"
LOCAL_HOST = "local"  # the orchestrator's own host: the default of every host: key


@dataclass(frozen=True)
class RestartPolicy:
    """When the orchestrator restarts a component that exited, and how often."""

    mode: str = "on-failure"
    max_restarts: int = 5
    backoff: float = 0.5  # seconds before the first restart; doubles each time
    max_backoff: float = 10.0

    def delay(self, restarts_so_far: int) -> float:
        """Seconds to wait before restart number ``restarts_so_far + 1``."""
        return float(min(self.max_backoff, self.backoff * (2 ** restarts_so_far)))

    def should_restart(self, exit_code: int, restarts_so_far: int) -> bool:
        """Whether a component that exited with ``exit_code`` is started again."""
        if self.mode == "never" or restarts_so_far >= self.max_restarts:
            return False
        return self.mode == "always" or exit_code != 0


@dataclass
class ComponentConfig:
    """One component of a subarchitecture."""

    id: str
    subarchitecture: str
    language: str = "python"
    kind: str = "unmanaged"
    cls: str = ""  # python: module:Class; java: fully.qualified.Class; other: unused (ignored)
    run: str = ""  # cpp: executable (absolute, relative to base_dir, or a bare name looked up); other: as written
    command: list[str] = field(default_factory=list)  # other: run: as words, the first resolved like cpp's run:
    args: dict[str, Any] = field(default_factory=dict)
    privileged: bool = False
    in_process: bool = False
    manual: bool = False  # started by hand (`cast token`), not by the orchestrator
    restart: RestartPolicy = field(default_factory=RestartPolicy)
    quota: Quota | None = None  # what it may hold on each server (entries, bytes; 0: unbounded)
    classpath: list[str] = field(default_factory=list)  # java: extra entries, absolute
    host: str = LOCAL_HOST  # where it runs: local, or a name under hosts: (started by that host's agent)
    ros: RosBridgeConfig | None = None  # ros: the bridge's ROS generation, node and mappings (docs/ros.md)
    base_dir: Path = field(default_factory=Path.cwd)  # directory of the file that defines it
    position: Position = field(default_factory=lambda: Position("<config>"))
    positions: dict[str, Position] = field(default_factory=dict)  # of each key's value, for later checks

    def at(self, key: str) -> Position:
        """Where the value of ``key`` is written (the component itself if not written)."""
        return self.positions.get(key, self.position)

    @property
    def remote(self) -> bool:
        """Whether it runs on another host, started by that host's agent."""
        return self.host != LOCAL_HOST

    @property
    def launched(self) -> bool:
        """Whether the orchestrator starts this component as its own process."""
        return not (self.in_process or self.manual)


@dataclass
class SubarchitectureConfig:
    """One subarchitecture: its task manager policy and its components."""

    name: str
    policy: str = "always"
    policy_options: dict[str, Any] = field(default_factory=dict)
    components: dict[str, ComponentConfig] = field(default_factory=dict)
    position: Position = field(default_factory=lambda: Position("<config>"))

    def make_policy(self) -> TaskPolicy:
        """The task manager policy object."""
        return make_policy(self.policy, self.policy_options)


@dataclass(frozen=True)
class PersistenceConfig:
    """Where a server keeps its working memories, and when a write counts as done.

    ``durability``: ``always`` (each write fsynced before it is acknowledged),
    ``batch`` (group commit, still acknowledged only once durable) or ``none``
    (written in the background; a crash may lose acknowledged writes).
    """

    path: Path
    durability: str = "batch"


@dataclass(frozen=True)
class TlsConfig:
    """TLS for every server of the system and the components' connections.

    Servers present ``cert``/``key``; clients verify them against ``ca``. With
    ``client_auth`` servers also require a client certificate signed by ``ca``:
    launched components and tools present ``client_cert``/``client_key``, or
    ``cert``/``key`` when those are not given (a certificate that must then
    allow client use too).
    """

    ca: Path
    cert: Path
    key: Path
    client_auth: bool = False
    client_cert: Path | None = None
    client_key: Path | None = None

    @property
    def component_identity(self) -> tuple[Path, Path]:
        """The certificate and key launched components present when servers require one."""
        if self.client_cert is not None and self.client_key is not None:
            return self.client_cert, self.client_key
        return self.cert, self.key


@dataclass(frozen=True)
class AuthConfig:
    """Token rules: whether reads need a token, and how long issued tokens live (0: forever)."""

    reads_require_token: bool = True
    token_ttl: float = 0.0


@dataclass
class ServerConfig:
    """One server process: where it listens and which SAs it hosts."""

    name: str
    listen: str = DEFAULT_LISTEN
    subarchitectures: list[str] = field(default_factory=list)
    persistence: PersistenceConfig | None = None
    host: str = LOCAL_HOST  # another host's agent starts it (docs/multihost.md); the first server stays local
    advertise: str = ""  # HOST:PORT other hosts use to reach it ("": its listen address; port 0: its port)

    def address(self, endpoint: str) -> str:
        """What other hosts dial: ``advertise`` (port 0: the bound port of ``endpoint``), else ``endpoint``."""
        if not self.advertise:
            return endpoint
        host, _, port = self.advertise.rpartition(":")
        return f"{host}:{endpoint.rpartition(':')[2]}" if int(port) == 0 else self.advertise


@dataclass(frozen=True)
class HostConfig:
    """Another machine of the system: where its ``cast agent`` listens, and TLS to reach it."""

    name: str
    agent: str
    tls_ca: Path | None = None
    tls_cert: Path | None = None
    tls_key: Path | None = None


@dataclass
class ImagesConfig:
    """Container images for ``cast export --to kubernetes`` (docs/deploy.md): one per language runtime.

    ``python`` also runs the servers and the token containers. ``components``
    gives a component an image of its own (needed by ``language: other`` ones).
    The defaults are the tags docs/deploy.md builds from ``deploy/images/``.
    """

    python: str = "cast-python:0.1.0"
    cpp: str = "cast-cpp:0.1.0"
    java: str = "cast-java:0.1.0"
    pull_policy: str = "IfNotPresent"
    components: dict[str, str] = field(default_factory=dict)

    def for_component(self, comp: ComponentConfig) -> str:
        """The image a component's container runs ("" for an ``other`` one without an image of its own)."""
        if comp.id in self.components:
            return self.components[comp.id]
        return {"python": self.python, "cpp": self.cpp, "java": self.java}.get(comp.language, "")


@dataclass
class OrchestratorOptions:
    """How ``cast run`` supervises the system."""

    connect_timeout: float = 60.0  # seconds to wait for every component to connect
    stop_timeout: float = 10.0  # seconds between SIGTERM and SIGKILL
    lease_ms: int = 10_000  # session lease without heartbeats


@dataclass
class SystemConfig:
    """A whole system."""

    name: str
    subarchitectures: dict[str, SubarchitectureConfig]
    limits: Limits = field(default_factory=Limits)
    shared_memory: SharedSettings = field(default_factory=SharedSettings)
    source: str = "<config>"
    servers: list[ServerConfig] = field(default_factory=list)
    python_path: list[Path] = field(default_factory=list)
    orchestrator: OrchestratorOptions = field(default_factory=OrchestratorOptions)
    variables: dict[str, str] = field(default_factory=dict)
    files: list[Path] = field(default_factory=list)
    tls: TlsConfig | None = None
    auth: AuthConfig = field(default_factory=AuthConfig)
    hosts: dict[str, HostConfig] = field(default_factory=dict)
    images: ImagesConfig = field(default_factory=ImagesConfig)  # for cast export --to kubernetes

    def __post_init__(self) -> None:
        if not self.servers:
            self.servers = [ServerConfig("main", DEFAULT_LISTEN, list(self.subarchitectures))]

    @property
    def components(self) -> list[ComponentConfig]:
        """Every component, in file order (the order they are started in)."""
        return [c for sa in self.subarchitectures.values() for c in sa.components.values()]

    def component(self, component_id: str) -> ComponentConfig | None:
        """A component by id."""
        return next((c for c in self.components if c.id == component_id), None)

    @property
    def remote_components(self) -> list[ComponentConfig]:
        """The launched components that run on another host."""
        return [c for c in self.components if c.launched and c.remote]

    def server_of(self, sa: str) -> ServerConfig:
        """The server hosting an SA."""
        return next(s for s in self.servers if sa in s.subarchitectures)
