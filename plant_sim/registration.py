"""Registering a simulator's loops with the tuner's admin API (``POST /loops``)."""

from __future__ import annotations

from plant_sim.config import LoopSpec
from service.gateways.registration import RegistrationError, TunerApi, check_not_foreign


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
    tuner already had (HTTP 409), which a restarted simulator resumes; a RegistrationError
    when another gateway's loop has the id. Calls retry while the tuner may still be
    starting, for up to ``timeout`` s (:class:`TunerApi`)."""
    known = {}
    with TunerApi(url, token, timeout=timeout, request_timeout=10.0) as api:
        for spec in specs:
            what = f"registering {spec.loop_id}"
            response = api.call("POST", "/loops", what=what, json=spec.registration(scan, gateway))
            if response.status_code == 409:
                check_not_foreign(response, spec.loop_id, gateway)
                response = api.call("GET", f"/loops/{spec.loop_id}", what=what)
                if response.is_success:
                    known[spec.loop_id] = response.json()
                    continue
            if not response.is_success:
                raise RegistrationError(
                    f"{what} failed: HTTP {response.status_code} {response.text[:300]}"
                )
    return known
