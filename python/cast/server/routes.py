"""Where each SA of a system is served, as a server's directory tells components."""

from __future__ import annotations

from dataclasses import dataclass, field

__all__ = ["Routes"]


@dataclass
class Routes:
    """The endpoints of this server's SAs and, in a system of several servers, of the others'."""

    local: dict[str, str]  # SA hosted here -> this server's endpoint (empty until it listens)
    remote: dict[str, str] = field(default_factory=dict)  # SA of another server -> its endpoint

    @classmethod
    def of(cls, subarchitectures: list[str]) -> Routes:
        """Routes of a server hosting ``subarchitectures``, before it listens."""
        return cls({sa: "" for sa in subarchitectures})

    def listening(self, endpoint: str) -> None:
        """The server listens at ``endpoint``: its own SAs are served there."""
        for sa in self.local:
            self.local[sa] = endpoint

    @property
    def endpoint(self) -> str:
        """This server's endpoint ("" before it listens)."""
        return next(iter(self.local.values()), "")
