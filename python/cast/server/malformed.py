"""Requests whose bytes do not parse get INVALID_ARGUMENT, not gRPC's UNKNOWN.

grpc answers a request its deserializer cannot parse with UNKNOWN ("Exception
deserializing request"), which says nothing a client can act on. Here each
request deserializer is wrapped once, when the services are registered: bytes
that do not parse become a :class:`Malformed` request, and the first thing a
servicer reads from it raises InvalidArgumentError, which the servicers' usual
error handling turns into INVALID_ARGUMENT naming the request type. A request
that parses costs one extra function call; nothing is done per call otherwise.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import grpc
from google.protobuf.message import DecodeError

from cast.errors import InvalidArgumentError

__all__ = ["Malformed", "SafeRegistrar"]


class Malformed:
    """Stands for a request whose bytes did not parse; reading anything from it raises INVALID_ARGUMENT."""

    __slots__ = ("_message",)

    def __init__(self, message: str) -> None:
        object.__setattr__(self, "_message", message)

    def __getattr__(self, name: str) -> Any:
        raise InvalidArgumentError(object.__getattribute__(self, "_message"))


def _safe(deserializer: Callable[[bytes], Any] | None, path: str) -> Callable[[bytes], Any] | None:
    if deserializer is None:
        return None
    original = deserializer

    def parse(data: bytes) -> Any:
        try:
            return original(data)
        except (DecodeError, ValueError, RuntimeError) as exc:
            return Malformed(
                f"request bytes for {path} do not parse ({exc}): send a serialised message of the method's "
                "request type"
            )

    return parse


def _wrap(handler: Any, path: str) -> Any:
    if handler is None or getattr(handler, "request_deserializer", None) is None:
        return handler
    return handler._replace(request_deserializer=_safe(handler.request_deserializer, path))


class SafeRegistrar:
    """Stands in for a server when services are added: wraps every request deserializer once.

    It also keeps services off grpcio's "registered methods": the generated helpers
    register every method twice, in a generic handler and as a registered method,
    and with grpcio 1.85's grpc.aio a server that has registered methods spends
    about 13% more instructions on every unary call, registered or not (callgrind,
    a server of these services: 680k instructions per Overwrite against 592k
    without them). The generic handlers serve the same methods, so only those
    are kept. ``wrap=False`` keeps the deserializers as they are (health and
    reflection, whose servicers are not ours).
    """

    def __init__(self, server: grpc.aio.Server, wrap: bool = True) -> None:
        self._server = server
        self._wrap = wrap

    def add_generic_rpc_handlers(self, handlers: Sequence[Any]) -> None:
        """Wrap the handlers of dictionary-based generic handlers in place, then register them."""
        if self._wrap:
            for generic in handlers:
                table = getattr(generic, "_method_handlers", None)
                if isinstance(table, dict):
                    for path in list(table):
                        table[path] = _wrap(table[path], path)
        self._server.add_generic_rpc_handlers(handlers)

    def add_registered_method_handlers(self, service: str, handlers: dict[str, Any]) -> None:
        """Ignored: the same methods are served by the generic handler registered alongside."""
