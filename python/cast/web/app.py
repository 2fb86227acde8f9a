"""The web application (Starlette): the page, its JSON API, the live stream, and the door in front of them.

Routes (docs/web.md, "The API"): ``/`` the page; ``/api/state`` the
architecture, task managers and rates; ``/api/entries?sa=SA[&type=TYPE]``;
``/api/entry?sa=SA&id=ID`` one value as JSON; ``/api/events`` a server-sent
event stream (``state`` on every refresh, ``changes`` as they come);
``/login`` the login link's target and the token form; ``/static/`` the page's
files. Every route but ``/login`` and ``/static/`` needs a session or a token
(:mod:`cast.web.access`). The sync endpoints make blocking gRPC calls: Starlette
runs them on its thread pool, never on the event loop.
"""

from __future__ import annotations

import asyncio
import html
import json
import threading
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import HTMLResponse, JSONResponse, RedirectResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles
from starlette.types import ASGIApp, Receive, Scope, Send

from cast.errors import CastError
from cast.web.access import COOKIE, Access
from cast.web.model import LiveModel

__all__ = ["STATIC", "make_app"]

STATIC = Path(__file__).resolve().parent / "static"
"""The page's files (package data)."""

_HTML_HEADERS = {
    # Only our own files run: no inline script, nothing from elsewhere, never inside another site's frame.
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; frame-ancestors 'none'",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cache-Control": "no-store",
}
_STATUS = {"NOT_FOUND": 404, "INVALID_ARGUMENT": 400, "UNAVAILABLE": 503, "DEADLINE_EXCEEDED": 504}
_TICK_S = 0.2  # how often a live stream looks for news
_KEEPALIVE_S = 15.0


def _login_page(message: str, status: int) -> HTMLResponse:
    page = (STATIC / "login.html").read_text().replace("{{message}}", html.escape(message))
    return HTMLResponse(page, status, headers=_HTML_HEADERS)


def _refused(path: str, status: int, why: str) -> Response:
    if path.startswith("/api/"):
        return JSONResponse({"error": why}, status)
    return _login_page(why, status)


class RequireAccess:
    """ASGI middleware: a request without a session or an accepted token is refused (401, or 403 for a bad token)."""

    def __init__(self, app: ASGIApp, access: Access) -> None:
        self.app = app
        self.access = access

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        if scope["type"] != "http" or path == "/login" or path.startswith("/static/"):
            await self.app(scope, receive, send)
            return
        request = Request(scope)
        if self.access.session_ok(request.cookies.get(COOKIE)):
            await self.app(scope, receive, send)
            return
        scheme, _, token = request.headers.get("authorization", "").partition(" ")
        if scheme.lower() == "bearer" and token:
            try:
                accepted = await run_in_threadpool(self.access.token_ok, token)
            except CastError as exc:
                await _refused(path, 503, f"cannot check the token: {exc.message}")(scope, receive, send)
                return
            if accepted:
                await self.app(scope, receive, send)
                return
            response = _refused(path, 403, "the system does not accept this token (not signed with its secret, or "
                                           "expired): make one with `cast token NAME --sa SA`")
        else:
            response = _refused(path, 401, "not signed in: open the login link `cast web` printed (each link works "
                                           "once), or give a CAST token")
        await response(scope, receive, send)


def _error(exc: CastError) -> JSONResponse:
    return JSONResponse({"error": exc.message, "code": exc.code}, _STATUS.get(exc.code, 502))


def _sse(event: str, data: Any) -> str:
    text = data if isinstance(data, str) else json.dumps(data, separators=(",", ":"))
    return f"event: {event}\ndata: {text}\n\n"


def make_app(model: LiveModel, access: Access, closing: threading.Event) -> Starlette:
    """The application showing ``model`` behind ``access``; live streams end when ``closing`` is set."""
    index = (STATIC / "index.html").read_text()

    def page(_request: Request) -> Response:
        return HTMLResponse(index, headers=_HTML_HEADERS)

    async def login(request: Request) -> Response:
        if request.method == "POST":
            form = parse_qs((await request.body()).decode("utf-8", "replace"))
            token = (form.get("token") or [""])[0]
            try:
                session = await run_in_threadpool(access.session_for_token, token)
            except CastError as exc:
                return _login_page(f"cannot check the token: {exc.message}", 503)
            if session is None:
                return _login_page("the system does not accept this token (not signed with its secret, or expired)",
                                   403)
        else:
            key = request.query_params.get("key")
            if key is None:
                return _login_page("", 200)
            session = access.spend_key(key)
            if session is None:
                return _login_page("this login link was used already, or is not this view's: open the newest link "
                                   "`cast web` printed (each works once), or give a token", 403)
        response = RedirectResponse("/", 303)
        response.set_cookie(COOKIE, session, httponly=True, samesite="strict", path="/")
        return response

    def state(_request: Request) -> Response:
        return Response(model.state()[1], media_type="application/json", headers={"Cache-Control": "no-store"})

    def entries(request: Request) -> Response:
        sa = request.query_params.get("sa", "")
        if not sa:
            return JSONResponse({"error": "give ?sa=SA (and optionally &type=TYPE)"}, 400)
        try:
            return JSONResponse(model.entries(sa, request.query_params.get("type", "")))
        except CastError as exc:
            return _error(exc)

    def entry(request: Request) -> Response:
        sa, entry_id = request.query_params.get("sa", ""), request.query_params.get("id", "")
        if not sa or not entry_id:
            return JSONResponse({"error": "give ?sa=SA&id=ID"}, 400)
        try:
            return JSONResponse(model.value(sa, entry_id))
        except CastError as exc:
            return _error(exc)

    async def events(_request: Request) -> Response:
        async def stream() -> AsyncIterator[str]:
            version, seq, quiet_since = -1, 0, time.monotonic()
            while not closing.is_set():
                now_version, text = model.state()
                sent = False
                if now_version != version:
                    version = now_version
                    yield _sse("state", text)
                    sent = True
                changes = model.feed.since(seq)
                if changes:
                    seq = changes[-1]["seq"]
                    yield _sse("changes", changes)
                    sent = True
                if sent:
                    quiet_since = time.monotonic()
                elif time.monotonic() - quiet_since > _KEEPALIVE_S:
                    yield ": keep-alive\n\n"  # so that a proxy or the browser does not give up on a quiet system
                    quiet_since = time.monotonic()
                await asyncio.sleep(_TICK_S)

        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})

    routes = [
        Route("/", page),
        Route("/login", login, methods=["GET", "POST"]),
        Route("/api/state", state),
        Route("/api/entries", entries),
        Route("/api/entry", entry),
        Route("/api/events", events),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    return Starlette(routes=routes, middleware=[Middleware(RequireAccess, access=access)])
