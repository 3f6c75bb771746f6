"""What every HTTP request to the tuner passes before a route reads it, the one check of
the API token, and the limits on a request's body.

FastAPI reads and parses a request's body before it runs the route's dependencies, the
token check among them: an unauthenticated client's 24 MB body cost the tuner 570 MB
before its 401, and six at once 2.7 GB (a security review, session 36). So, outside the
app (:class:`Gate`, an ASGI middleware), in order:

1. **Host**: one of ``api_allowed_hosts`` (default: the loopback names when the API is
   bound to loopback; any otherwise). A web page whose DNS name is rebound to 127.0.0.1
   reaches a loopback API under its own name (DNS rebinding): refused, 400.
2. **Origin**: a change (any method but GET, HEAD, OPTIONS) sent by a browser from
   another origin (an ``Origin`` header naming another host, or ``null``): refused, 403.
   A web page's cross-site POST reached a loopback API without a token; gateways and
   scripts send no ``Origin``. With the Host checked, the Origin is worth comparing.
3. **Token**: a change to the REST API (``/loops``; the console has its sessions)
   without the bearer token, when one is set: refused, 401, before its body is read.

Then FastAPI's own body limits (``max_body_size``, the sizes below): a body over its
route's limit is refused, 413, by its ``Content-Length`` or as it streams in.
"""

from __future__ import annotations

import secrets
import urllib.parse

from starlette.datastructures import Headers
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from service.daemon.settings import Settings

LOOPBACK_NAMES = frozenset({"127.0.0.1", "localhost", "::1"})
"""Host names a loopback API answers to by default."""
BODY_BYTES = 1 << 20
"""Largest body of a request (1 MiB): a registration is about 300 bytes."""
BULK_BODY_BYTES = 64 << 20
"""Largest body of ``POST /loops/bulk`` (64 MiB): 100,000 loops (``MAX_BULK``) of up to
about 670 bytes each."""
LOGIN_BODY_BYTES = 16 << 10
"""Largest body of the console's login form (a token, a name, a path)."""
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


def token_matches(settings: Settings, given: str) -> bool:
    """``given`` is the API token (any is, when none is set: an open API)."""
    if settings.api_token is None:
        return True
    expected = settings.api_token.get_secret_value().encode()
    return secrets.compare_digest(given.encode(), expected)


def bearer(authorization: str | None) -> str:
    """The token of an ``Authorization: Bearer <token>`` header ('' without one)."""
    scheme, _, token = (authorization or "").partition(" ")
    return token.strip() if scheme.lower() == "bearer" else ""


def allowed_hosts(settings: Settings) -> frozenset[str] | None:
    """The host names the API answers to (None: any)."""
    if settings.api_allowed_hosts is not None:
        return frozenset(h.lower() for h in settings.api_allowed_hosts)
    return LOOPBACK_NAMES if settings.api_host in LOOPBACK_NAMES else None


def host_name(host: str) -> str:
    """The name of a ``Host`` header's value, without its port (``[::1]:80`` -> ``::1``)."""
    name = urllib.parse.urlsplit(f"//{host}").hostname
    return (name or "").lower()


def same_origin(headers: Headers) -> bool:
    """No ``Origin`` (not a browser), or one naming the host and port the request is to."""
    origin = headers.get("origin")
    if origin is None:
        return True
    return origin != "null" and urllib.parse.urlsplit(origin).netloc == headers.get("host", "")


class Gate:
    """The checks of the module doc, outside the app."""

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.settings = settings
        self.hosts = allowed_hosts(settings)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        refusal = self._refusal(scope, Headers(scope=scope))
        if refusal is None:
            await self.app(scope, receive, send)
            return
        code, detail, extra = refusal
        await JSONResponse({"detail": detail}, code, headers=extra)(scope, receive, send)

    def _refusal(self, scope: Scope, headers: Headers):
        """(status, detail, headers) of a request refused before the app sees it."""
        if self.hosts is not None and host_name(headers.get("host", "")) not in self.hosts:
            return 400, "unknown host (set PITUNE_API_ALLOWED_HOSTS to answer to it)", None
        change = scope["method"] not in SAFE_METHODS
        if change and not same_origin(headers):
            return 403, "cross-origin request refused", None
        rest = scope["path"] == "/loops" or scope["path"].startswith("/loops/")
        if (
            change
            and rest
            and not token_matches(self.settings, bearer(headers.get("authorization")))
        ):
            return 401, "missing or invalid bearer token", {"WWW-Authenticate": "Bearer"}
        return None
