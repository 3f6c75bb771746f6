"""Registering a simulator's loops with the tuner's admin API (``POST /loops``)."""

from __future__ import annotations

import time

import httpx

from plant_sim.config import LoopSpec


class RegistrationError(RuntimeError):
    pass


def register(
    url: str,
    specs: tuple[LoopSpec, ...],
    *,
    scan: float,
    token: str | None,
    timeout: float,
    gateway: str | None = None,
) -> dict[str, dict]:
    """Register each loop with the tuner (``POST /loops``); return the views of loops the
    tuner already had (HTTP 409), which a restarted simulator resumes.

    Retries connection failures until ``timeout``: the tuner may still be starting.
    """
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    deadline = time.monotonic() + timeout
    known = {}
    with httpx.Client(base_url=url, headers=headers, timeout=10.0) as client:

        def call(method: str, path: str, **kw) -> httpx.Response:
            while True:
                try:
                    response = client.request(method, path, **kw)
                except httpx.TransportError as exc:
                    if time.monotonic() > deadline:
                        raise RegistrationError(f"tuner API at {url} unreachable: {exc}") from exc
                    time.sleep(0.2)
                    continue
                # a proxy in front of a tuner still starting answers 502-504: retried too
                if response.status_code in (502, 503, 504) and time.monotonic() <= deadline:
                    time.sleep(0.5)
                    continue
                return response

        for spec in specs:
            response = call("POST", "/loops", json=spec.registration(scan, gateway))
            if response.status_code == 409:
                response = call("GET", f"/loops/{spec.loop_id}")
                if response.is_success:
                    known[spec.loop_id] = response.json()
                    continue
            if response.status_code == 401:
                raise RegistrationError(
                    f"registering {spec.loop_id} at {url} refused (HTTP 401): the tuner "
                    "requires its API token; set PITUNE_API_TOKEN to it"
                    + (" (the one given was refused)" if token else "")
                )
            if not response.is_success:
                raise RegistrationError(
                    f"registering {spec.loop_id} failed: HTTP {response.status_code} "
                    f"{response.text[:300]}"
                )
    return known
