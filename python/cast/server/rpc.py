"""Shared plumbing of the servicers: the caller's identity by the table of calls, errors to status codes.

Each handler is wrapped by :func:`rpc` or :func:`stream_rpc`, which looks its call up in
:data:`cast.core.calls.CALLS` (``<servicer's SERVICE>/<method>``), establishes the caller the
credential asks for, and hands it to the handler: no handler decides for itself whether it needs a
token.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any, TypeVar

import grpc

from cast.auth import TokenSigner
from cast.core.calls import Credential, credential
from cast.core.records import Identity
from cast.errors import ERROR_TRAILER, CastError, UnauthenticatedError, error_for_code

__all__ = ["ANONYMOUS", "Authenticator", "Context", "Servicer", "error_class", "rpc", "stream_rpc"]

log = logging.getLogger("cast.server")

Context = grpc.aio.ServicerContext[Any, Any]
"""The servicer context of any call (the servicers only read metadata and deadlines from it)."""

ANONYMOUS = Identity("anonymous", "", False)
"""Who reads without a token when ``auth.reads_require_token`` is false (it holds no locks, writes nothing)."""

Req = TypeVar("Req")
Resp = TypeVar("Resp")


class Authenticator:
    """Finds the caller's identity in the ``authorization: Bearer <token>`` metadata."""

    def __init__(self, signer: TokenSigner, reads_require_token: bool = True) -> None:
        self._signer = signer
        self.reads_require_token = reads_require_token

    def identify_read(self, context: Context) -> Identity:
        """The caller of a read: like :meth:`identify`, but anonymous if there is no token and reads are open.

        Reads are open when the configuration says ``auth.reads_require_token:
        false``; a bad token is refused all the same.
        """
        return self._read_until(context)[0]

    def _read_until(self, context: Context) -> tuple[Identity, float]:
        if not self.reads_require_token:
            metadata = context.invocation_metadata() or ()
            if not any(key == "authorization" for key, _ in metadata):
                return ANONYMOUS, 0.0
        return self.identify_until(context)

    def caller(self, context: Context, needs: Credential) -> Identity:
        """The caller of a call that needs ``needs`` (:mod:`cast.core.calls`)."""
        return self.caller_until(context, needs)[0]

    def caller_until(self, context: Context, needs: Credential) -> tuple[Identity, float]:
        """As :meth:`caller`, and when the answer must be established again (its token's expiry; 0: never)."""
        if needs is Credential.READ:
            return self._read_until(context)
        if needs is Credential.TOKEN:
            return self.identify_until(context)
        raise UnauthenticatedError(f"a server answers no call that needs {needs.value}")

    def verify(self, token: str) -> Identity:
        """The identity a token states (a shared-memory session's HELLO carries one); UNAUTHENTICATED if bad."""
        return self._signer.verify(token)

    def verify_until(self, token: str) -> tuple[Identity, float]:
        """As :meth:`verify`, and when the token expires (0: never)."""
        return self._signer.verify_until(token)

    def identify(self, context: Context) -> Identity:
        """The verified identity of the caller; UNAUTHENTICATED if the token is missing or bad."""
        return self.identify_until(context)[0]

    def identify_until(self, context: Context) -> tuple[Identity, float]:
        """As :meth:`identify`, and when the call's token expires (0: never): :meth:`TokenSigner.verify_until`."""
        for key, value in context.invocation_metadata() or ():
            if key == "authorization":
                text = value.decode() if isinstance(value, bytes) else value
                scheme, _, token = text.partition(" ")
                if scheme.lower() != "bearer" or not token:
                    raise UnauthenticatedError("authorization metadata must be 'Bearer <token>'")
                return self._signer.verify_until(token.strip())
        raise UnauthenticatedError(
            "no token: send 'authorization: Bearer <token>' metadata (components get CAST_TOKEN from the "
            "orchestrator or `cast token`)"
        )


# The classes a status code maps to by itself: no trailer needed.
_PLAIN = frozenset(type(error_for_code(code, "")).__name__ for code in (
    "ALREADY_EXISTS", "NOT_FOUND", "ABORTED", "PERMISSION_DENIED", "FAILED_PRECONDITION", "INVALID_ARGUMENT",
    "UNAUTHENTICATED", "DEADLINE_EXCEEDED", "OUT_OF_RANGE", "RESOURCE_EXHAUSTED", "UNAVAILABLE", "INTERNAL",
))


def error_class(exc: CastError) -> str:
    """The class name clients need besides the status code to raise ``exc``'s class; empty if the code says it.

    Several errors share a status code (FAILED_PRECONDITION is a held lock or a
    task in the wrong state): the name lets every client raise the same one.
    """
    name = type(exc).__name__
    return "" if name in _PLAIN else name


async def _abort(context: Context, exc: BaseException) -> None:
    if isinstance(exc, CastError):
        name = error_class(exc)
        if name:
            context.set_trailing_metadata(((ERROR_TRAILER, name),))
        await context.abort(grpc.StatusCode[exc.code], exc.message)
    log.exception("internal error in %s", context)
    await context.abort(grpc.StatusCode.INTERNAL, f"internal server error: {type(exc).__name__}: {exc}")


class Servicer:
    """A servicer of one ``cast.v1`` service: :attr:`SERVICE` names it, :attr:`auth` establishes callers."""

    SERVICE = ""
    auth: Authenticator

    def who(self, call: str, context: Context) -> Identity:
        """The caller of ``call`` (a method of :attr:`SERVICE`), by the table of calls."""
        return self.auth.caller(context, credential(f"{self.SERVICE}/{call}"))

    def who_until(self, call: str, context: Context) -> tuple[Identity, float]:
        """As :meth:`who`, and until when that answer holds (:meth:`Authenticator.caller_until`)."""
        return self.auth.caller_until(context, credential(f"{self.SERVICE}/{call}"))


Handler = Callable[[Any, Req, Context, Identity], Awaitable[Resp]]
StreamHandler = Callable[[Any, Any, Context, Identity], AsyncIterator[Resp]]


def rpc(fn: Handler[Req, Resp]) -> Callable[[Any, Req, Context], Awaitable[Resp]]:
    """Wrap a unary handler: its caller is established first.

    A raised CastError becomes its status code, anything else INTERNAL.
    """
    name = fn.__name__

    @functools.wraps(fn)
    async def wrapper(self: Servicer, request: Req, context: Context) -> Resp:
        try:
            return await fn(self, request, context, self.who(name, context))
        except Exception as exc:
            if isinstance(exc, grpc.aio.AbortError):
                raise
            await _abort(context, exc)
            raise AssertionError("unreachable") from exc

    return wrapper


def stream_rpc(fn: StreamHandler[Resp]) -> Callable[[Any, Any, Context], AsyncIterator[Resp]]:
    """Wrap a streaming handler the same way as :func:`rpc`."""
    name = fn.__name__

    @functools.wraps(fn)
    async def wrapper(self: Servicer, request: Any, context: Context) -> AsyncIterator[Resp]:
        try:
            async for item in fn(self, request, context, self.who(name, context)):
                yield item
        except Exception as exc:
            if isinstance(exc, grpc.aio.AbortError):
                raise
            await _abort(context, exc)

    return wrapper
