"""Registering loops with the tuner's admin API: the one retry rule every gateway and
simulator uses (``pitune plant run``, ``pitune gateway opcua``).

A gateway usually starts with (or before) its tuner, so a call is retried until a
deadline: connection failures (the API not listening yet) and 502-504 (a proxy in front
of a tuner still starting). Anything else is the tuner's answer. A 401 becomes a
:class:`RegistrationError` that says which variable holds the token.
"""

from __future__ import annotations

import time

import httpx

RETRY_STATUSES = (502, 503, 504)
RETRY_PAUSE_S = 0.5
"""Pause between two attempts: short next to a tuner's start-up (torch alone takes
seconds), long enough not to busy-loop."""


class RegistrationError(RuntimeError):
    """The loops could not be registered (the message says why and what to do)."""


def check_not_foreign(response: httpx.Response, loop_id: str, gateway: str | None) -> None:
    """After a 409 of registering ``loop_id`` for ``gateway``: raise a
    :class:`RegistrationError` when the id is taken by a loop of another gateway (the
    reply's ``gateways``, :class:`~service.daemon.schemas.Taken`). That loop is not this
    one: its samples on this gateway's key are rejected (``wrong_gateway``) and its
    gains go to the other gateway, so this loop would never be tuned. A loop of this
    gateway is this one registered before (a restart), and one of none is tuned from the
    samples this gateway sends on the loop's own key: both carry on."""
    try:
        taken = response.json().get("gateways") or {}
    except (ValueError, AttributeError):  # not the tuner's JSON (a proxy's page)
        return
    other = taken.get(loop_id) if isinstance(taken, dict) else None
    if other is not None and other != gateway:
        mine = f"this gateway {gateway!r}" if gateway else "this client, without a gateway"
        raise RegistrationError(
            f"loop {loop_id!r} is already registered with gateway {other!r}, not {mine}: "
            "this loop would never be tuned. Another gateway took the id: an admin must "
            f"delete that loop (DELETE /loops/{loop_id}), or one of the two must get another id"
        )


class TunerApi:
    """An admin-API client whose calls retry until ``timeout`` seconds after it was made;
    ``with TunerApi(...) as api: api.call("POST", "/loops", json=body)``."""

    def __init__(
        self,
        url: str,
        token: str | None,
        *,
        timeout: float,
        token_env: str = "PITUNE_API_TOKEN",
        request_timeout: float = 30.0,
    ) -> None:
        self.url = url
        self.token = token
        self.token_env = token_env
        self.deadline = time.monotonic() + timeout
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.client = httpx.Client(base_url=url, headers=headers, timeout=request_timeout)

    def __enter__(self) -> TunerApi:
        return self

    def __exit__(self, *exc: object) -> None:
        self.client.close()

    def call(self, method: str, path: str, *, what: str, **kw) -> httpx.Response:
        """The response (retried as the module says); ``what`` names the call in errors.
        Raises :class:`RegistrationError` when the API stays unreachable or answers 401."""
        while True:
            try:
                response = self.client.request(method, path, **kw)
            except httpx.TransportError as exc:
                if time.monotonic() > self.deadline:
                    raise RegistrationError(f"tuner API at {self.url} unreachable: {exc}") from exc
                time.sleep(RETRY_PAUSE_S)
                continue
            if response.status_code in RETRY_STATUSES and time.monotonic() <= self.deadline:
                time.sleep(RETRY_PAUSE_S)
                continue
            if response.status_code == 401:
                raise RegistrationError(
                    f"{what} at {self.url} refused (HTTP 401): the tuner requires its API "
                    f"token; set {self.token_env} to it"
                    + (" (the one given was refused)" if self.token else "")
                )
            return response
