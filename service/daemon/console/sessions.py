"""Console sessions: login with the API token once, then a session cookie and a CSRF token.

The login form checks the API token once and keeps only a session id in an HttpOnly,
SameSite=Strict cookie (the token itself never reaches the browser's storage or script);
each session has its own CSRF token, which the pages carry and every state-changing
request must send back (header ``X-CSRF-Token``, or the ``csrf`` form field of the logout
form). Requests whose ``Origin`` names another host are refused as well.
"""

from __future__ import annotations

import re
import secrets
import threading
import time
import urllib.parse
from dataclasses import dataclass, field

from fastapi import HTTPException, Request

COOKIE = "pitune_ui"
SESSION_IDLE_S = 8 * 3600.0
"""A session unused this long is logged out."""
MAX_SESSIONS = 1000
LOGIN_PENALTY_S = 1.0
"""Seconds a wrong token waits for its answer."""
ACTOR_NAME = re.compile(r"[^A-Za-z0-9_.@-]")
"""Characters stripped from the name typed at login (it becomes the audit's ``ui:<name>``)."""


@dataclass
class Session:
    csrf: str
    actor: str
    created: float
    seen: float = field(default_factory=time.monotonic)


class Sessions:
    """Console sessions in memory (a restart logs everyone out)."""

    def __init__(self) -> None:
        self._by_id: dict[str, Session] = {}
        self._lock = threading.Lock()

    def create(self, actor: str) -> tuple[str, Session]:
        sid = secrets.token_urlsafe(32)
        session = Session(csrf=secrets.token_urlsafe(32), actor=actor, created=time.time())
        with self._lock:
            self._expire()
            if len(self._by_id) >= MAX_SESSIONS:  # drop the least recently used
                oldest = min(self._by_id, key=lambda k: self._by_id[k].seen)
                del self._by_id[oldest]
            self._by_id[sid] = session
        return sid, session

    def get(self, sid: str | None) -> Session | None:
        if not sid:
            return None
        with self._lock:
            session = self._by_id.get(sid)
            if session is None:
                return None
            now = time.monotonic()
            if now - session.seen > SESSION_IDLE_S:
                del self._by_id[sid]
                return None
            session.seen = now
            return session

    def drop(self, sid: str | None) -> None:
        with self._lock:
            self._by_id.pop(sid or "", None)

    def _expire(self) -> None:
        now = time.monotonic()
        for sid in [k for k, s in self._by_id.items() if now - s.seen > SESSION_IDLE_S]:
            del self._by_id[sid]


def app_state(request: Request, name: str, factory):
    value = getattr(request.app.state, name, None)
    if value is None:
        value = factory()
        setattr(request.app.state, name, value)
    return value


def sessions_of(request: Request) -> Sessions:
    return app_state(request, "console_sessions", Sessions)


def session_of(request: Request) -> Session | None:
    return sessions_of(request).get(request.cookies.get(COOKIE))


def acting(request: Request) -> Session:
    """The session of a state-changing request: logged in, CSRF token and origin right."""
    session = session_of(request)
    if session is None:
        raise HTTPException(401, "log in to the console first (the API token)")
    given = request.headers.get("x-csrf-token", "")
    if not secrets.compare_digest(given.encode(), session.csrf.encode()):
        raise HTTPException(403, "missing or wrong CSRF token")
    return session  # (its origin: checked for every change, service.daemon.gate)


def safe_next(target: str) -> str:
    """Only a path of the console (no scheme, no host: no open redirect)."""
    parts = urllib.parse.urlsplit(target)
    if parts.scheme or parts.netloc or not parts.path.startswith("/ui") or "\\" in target:
        return "/ui"
    return parts.path
