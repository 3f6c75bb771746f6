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
   Behind a reverse proxy that passes its upstream's ``Host`` (nginx's default:
   ``127.0.0.1:8750``) the browser's Origin names the proxy's host instead: it is this
   API's too when it names one of the ``api_allowed_hosts`` set by name, with the scheme
   a trusted proxy forwarded (:func:`proxied_origin`). Only names set explicitly, never
   a ``*``, and only with a forwarded scheme: any other page's Origin is still refused.
3. **Token**: a change to the REST API (``/loops``, ``/hold``; the console has its sessions)
   without the bearer token, when one is set: refused, 401, before its body is read.
   A gateway's token (``api_gateway_tokens``) may only register loops: any other change
   with it is refused, 403, and the registration routes refuse loops of another gateway
   (:func:`registering_gateway`). A gateway host then holds no admin credential (with
   the admin token it held, one raised another gateway's loop to kp_max = 1e6 and
   deleted it).
   A client with :data:`MAX_FAILURES` wrong tokens (here or at the console's login)
   within :data:`FAILURE_WINDOW_S` is refused, 429, until the window has passed, and
   each lock-out is a WARNING: the REST check took 880 guesses a second, unlogged, and
   200 concurrent console logins finished in 1.3 s despite the login's 1 s penalty.

Then FastAPI's own body limits (``max_body_size``, the sizes below): a body over its
route's limit is refused, 413, by its ``Content-Length`` or as it streams in.
"""

from __future__ import annotations

import collections
import ipaddress
import logging
import secrets
import threading
import time
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
MAX_FAILURES = 10
"""Wrong tokens a client may give within :data:`FAILURE_WINDOW_S` (typos, a stale
script) before it is locked out for the rest of the window."""
FAILURE_WINDOW_S = 60.0
CLIENTS_KEPT = 10_000
"""Clients whose failures are remembered at most (the oldest forgotten first)."""
log = logging.getLogger("pitune.api")


class Failures:
    """Recent wrong tokens per client address (thread-safe: the console's login runs on
    the event loop, and so does the gate; the lock keeps it simple)."""

    def __init__(self) -> None:
        self._times: collections.OrderedDict[str, collections.deque[float]] = (
            collections.OrderedDict()
        )
        self._lock = threading.Lock()

    def _recent(self, client: str, now: float) -> collections.deque[float]:
        times = self._times.get(client)
        if times is None:
            return collections.deque()
        while times and times[0] <= now - FAILURE_WINDOW_S:
            times.popleft()
        return times

    def lockout(self, client: str) -> tuple[str, dict[str, str]] | None:
        """(detail, headers) of the 429 while the client is locked out, else None."""
        now = time.monotonic()
        with self._lock:
            times = self._recent(client, now)
            if len(times) < MAX_FAILURES:
                return None
            wait = times[0] + FAILURE_WINDOW_S - now
        detail = f"too many wrong tokens from this address; retry in {wait:.0f} s"
        return detail, {"Retry-After": str(max(1, round(wait)))}

    def failed(self, client: str, where: str) -> None:
        """A wrong token from ``client`` (``where``: the REST API or the console)."""
        now = time.monotonic()
        with self._lock:
            times = self._recent(client, now)
            times.append(now)
            self._times[client] = times
            self._times.move_to_end(client)
            while len(self._times) > CLIENTS_KEPT:
                self._times.popitem(last=False)
            count = len(times)
        if count == 1 or count == MAX_FAILURES:
            log.warning(
                "wrong API token from %s (%s): %s", client, where,
                "first in this minute" if count == 1
                else f"{count} within {FAILURE_WINDOW_S:g} s: locked out until they age",
            )  # fmt: skip


def client_of(scope: Scope) -> str:
    """The client address of a request (as the trusted proxies, if any, report it)."""
    client = scope.get("client")
    return client[0] if client else "?"


def token_matches(settings: Settings, given: str) -> bool:
    """``given`` is the API token (any is, when none is set: an open API)."""
    if settings.api_token is None:
        return True
    expected = settings.api_token.get_secret_value().encode()
    return secrets.compare_digest(given.encode(), expected)


def gateway_of(settings: Settings, given: str) -> str | None:
    """The gateway whose token ``given`` is (None: no gateway's)."""
    found = None
    for gateway, token in settings.api_gateway_tokens.items():  # every one compared
        if secrets.compare_digest(given.encode(), token.get_secret_value().encode()):
            found = gateway
    return found


REGISTRATION = frozenset({("POST", "/loops"), ("POST", "/loops/bulk")})
"""What a gateway's token may change."""
REST = ("/loops", "/hold")
"""The REST API's paths (and those below them) whose changes need the token."""


def is_rest(path: str) -> bool:
    return any(path == top or path.startswith(f"{top}/") for top in REST)


def registering_gateway(scope: Scope) -> str | None:
    """The gateway whose token the gate let this registration through with (None: the
    admin token, or none needed)."""
    return scope.get("state", {}).get("gateway_token_of")


def bearer(authorization: str | None) -> str:
    """The token of an ``Authorization: Bearer <token>`` header ('' without one)."""
    scheme, _, token = (authorization or "").partition(" ")
    return token.strip() if scheme.lower() == "bearer" else ""


def is_loopback(host: str) -> bool:
    """``host`` (an address the API binds to) is this machine's loopback only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may resolve to anything
        return False


def allowed_hosts(settings: Settings) -> frozenset[str] | None:
    """The host names the API answers to (None: any)."""
    if settings.api_allowed_hosts is not None:
        return frozenset(h.lower() for h in settings.api_allowed_hosts)
    return LOOPBACK_NAMES if is_loopback(settings.api_host) else None


def host_name(host: str) -> str:
    """The name of a ``Host`` header's value, without its port (``[::1]:80`` -> ``::1``)."""
    try:
        name = urllib.parse.urlsplit(f"//{host}").hostname
    except ValueError:  # not a host ("[::1"): no name, refused
        return ""
    return (name or "").lower()


def origin_hosts(settings: Settings) -> frozenset[str]:
    """The host names a proxied browser's Origin may name (:func:`proxied_origin`): the
    allowed hosts set by name. Not the loopback default, not "any", and no name with a
    ``*`` (a wildcard would make every page's Origin this API's: CSRF)."""
    names = settings.api_allowed_hosts or []
    return frozenset(h.lower() for h in names if "*" not in h)


def same_origin(scope: Scope, headers: Headers, proxied_hosts: frozenset[str]) -> bool:
    """No ``Origin`` (not a browser), one naming the host and port the request is to, or
    one a trusted proxy forwarded (:func:`proxied_origin`)."""
    origin = headers.get("origin")
    if origin is None:
        return True
    try:
        parts = urllib.parse.urlsplit(origin)
        name = (parts.hostname or "").lower()
    except ValueError:  # not a URL ("http://[evil"): not this origin
        return False
    if origin == "null":
        return False
    if parts.netloc == headers.get("host", ""):
        return True
    return proxied_origin(scope, headers, parts.scheme, name, proxied_hosts)


def proxied_origin(
    scope: Scope, headers: Headers, scheme: str, name: str, proxied_hosts: frozenset[str]
) -> bool:
    """An Origin of ``scheme://name[:port]`` behind a reverse proxy: ``name`` one of
    :func:`origin_hosts`, ``scheme`` the ``X-Forwarded-Proto`` of the request as the
    server took it. uvicorn takes that header only from ``api_trusted_proxies``
    (``forwarded_allow_ips``): from anyone else the request's scheme stays the
    connection's, http, so an https Origin is refused. A browser's cross-site request
    cannot set the header itself (a custom header: CORS, which the API does not allow),
    and its Origin is the page's own, whatever the header."""
    forwarded = headers.get("x-forwarded-proto", "").strip().lower()
    return (
        bool(forwarded)
        and scope.get("scheme") == forwarded == scheme.lower()
        and name in proxied_hosts
    )


class Gate:
    """The checks of the module doc, outside the app."""

    def __init__(self, app: ASGIApp, settings: Settings, failures: Failures) -> None:
        self.app = app
        self.settings = settings
        self.hosts = allowed_hosts(settings)
        self.origin_hosts = origin_hosts(settings)
        self.failures = failures

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
        if change and not same_origin(scope, headers, self.origin_hosts):
            return 403, "cross-origin request refused", None
        rest = is_rest(scope["path"])
        if change and (rest or scope["path"] == "/ui/login"):
            locked = self.failures.lockout(client_of(scope))
            if locked is not None:
                return 429, *locked
        given = bearer(headers.get("authorization"))
        if not (change and rest) or token_matches(self.settings, given):
            return None
        gateway = gateway_of(self.settings, given) if given else None
        if gateway is None:
            self.failures.failed(client_of(scope), "REST API")
            return 401, "missing or invalid bearer token", {"WWW-Authenticate": "Bearer"}
        if (scope["method"], scope["path"]) not in REGISTRATION:
            return 403, f"gateway {gateway!r}'s token may only register its loops", None
        scope.setdefault("state", {})["gateway_token_of"] = gateway
        return None
