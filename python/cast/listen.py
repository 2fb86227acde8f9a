"""Where a tool that serves people listens (``cast foxglove``, ``cast web``, and both in ``cast run``).

The address forms their ``--listen`` options take, and the error of an address they cannot bind.
"""

from __future__ import annotations

import ipaddress
import re
from dataclasses import dataclass

from cast.errors import CastError, InvalidArgumentError

__all__ = ["ListenAddress", "ListenError", "parse_listen"]

_HOST_PORT = re.compile(r"^(?:\[(?P<v6>[0-9A-Fa-f:.%\w]+)\]|(?P<host>[^:\[\]\s]+)):(?P<port>\d{1,5})$")


class ListenError(CastError):
    """A tool cannot listen where it was told (the address is taken or not this machine's)."""

    code = "UNAVAILABLE"


@dataclass(frozen=True)
class ListenAddress:
    """Where a tool listens: host and port (0: a free port, told once bound)."""

    host: str
    port: int

    @property
    def loopback(self) -> bool:
        """Whether only this machine can connect (127.0.0.0/8, ::1, localhost)."""
        if self.host == "localhost":
            return True
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return False  # a host name: it may resolve to any interface

    def url(self, scheme: str, port: int | None = None) -> str:
        """``scheme://HOST:PORT`` (with the bound port, if given)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{scheme}://{host}:{self.port if port is None else port}"


def parse_listen(text: str, option: str, example: str) -> ListenAddress:
    """``HOST:PORT``, ``[IPv6]:PORT`` or a bare ``PORT`` (on 127.0.0.1).

    InvalidArgumentError naming ``option`` and showing ``example`` (the tool's default) otherwise.
    """
    given = text.strip()
    match = _HOST_PORT.match(f"127.0.0.1:{given}" if given.isdigit() else given)
    port = int(match.group("port")) if match else -1
    if match is None or not 0 <= port <= 65535:
        raise InvalidArgumentError(
            f"{option} {text!r}: give HOST:PORT with a port from 0 to 65535, such as {example} (the default) or "
            "127.0.0.1:0 for a free port; [::1]:PORT for IPv6")
    return ListenAddress(match.group("v6") or match.group("host"), port)
