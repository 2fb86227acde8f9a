"""Who may see the page: the holder of a one-time login link, or of a token the system accepts.

``cast web`` prints a login link with a random key. Opening it once starts a
browser session (a random cookie, ``HttpOnly``, ``SameSite=Strict``) and spends
the key; a new link is printed for the next browser. A script (or a browser
with no link at hand) shows a CAST token instead, one the system's directory
accepts (``Authorization: Bearer TOKEN`` on each request, or the form at
``/login``). Everything but the login page and the page's static files is
refused without one of them: 401 with no credentials, 403 with wrong ones.
"""

from __future__ import annotations

import hmac
import secrets
import threading
import time
from collections import OrderedDict
from collections.abc import Callable

__all__ = ["COOKIE", "Access"]

COOKIE = "cast_web_session"
"""The name of the session cookie."""

_MAX_SESSIONS = 1000
_TOKEN_CACHE_S = 30.0


class Access:
    """The login key of the moment, the browser sessions started, and tokens recently checked.

    ``check_token`` asks the system whether it accepts a token (blocking).
    ``on_login`` is told the new login link each time one is spent.
    """

    def __init__(self, check_token: Callable[[str], bool], on_login: Callable[[str], None] | None = None) -> None:
        self._check_token = check_token
        self._on_login = on_login or (lambda _link: None)
        self._mutex = threading.Lock()
        self._key = secrets.token_urlsafe(24)
        self._sessions: OrderedDict[str, float] = OrderedDict()
        self._tokens: dict[str, float] = {}  # token -> until when it counts as checked
        self.base_url = ""

    def login_link(self) -> str:
        """The link that starts a browser session, once (``base_url`` must be set)."""
        with self._mutex:
            return f"{self.base_url}/login?key={self._key}"

    def spend_key(self, key: str) -> str | None:
        """A new session id for the current key (which is then spent, and the next link announced); else None."""
        with self._mutex:
            if not key or not hmac.compare_digest(key.encode(), self._key.encode()):
                return None
            self._key = secrets.token_urlsafe(24)
            session = self._new_session()
            link = f"{self.base_url}/login?key={self._key}"
        self._on_login(link)
        return session

    def session_for_token(self, token: str) -> str | None:
        """A new session id if the system accepts ``token`` (blocking: asks the system); else None."""
        if not self.token_ok(token):
            return None
        with self._mutex:
            return self._new_session()

    def _new_session(self) -> str:
        session = secrets.token_urlsafe(32)
        self._sessions[session] = time.time()
        while len(self._sessions) > _MAX_SESSIONS:
            self._sessions.popitem(last=False)  # the oldest browser signs in again
        return session

    def session_ok(self, session: str | None) -> bool:
        """Whether a session cookie is one this view handed out."""
        if not session:
            return False
        with self._mutex:
            return session in self._sessions

    def token_ok(self, token: str) -> bool:
        """Whether the system accepts ``token`` (asked at most every 30 s per token; blocking)."""
        token = token.strip()
        if not token:
            return False
        now = time.monotonic()
        with self._mutex:
            if self._tokens.get(token, 0.0) > now:
                return True
        if not self._check_token(token):
            return False
        with self._mutex:
            if len(self._tokens) > _MAX_SESSIONS:
                self._tokens.clear()
            self._tokens[token] = now + _TOKEN_CACHE_S
        return True
