"""The gateway's bulk registration of its loops with the tuner (the map's ``[tuner]``),
made once the gains in force are known, before sampling starts."""

from __future__ import annotations

import logging
import os

from service.gateways.opcua.loops import LoopRuntime
from service.gateways.opcua.sitemap import SiteMap
from service.gateways.registration import RegistrationError, TunerApi, check_not_foreign

log = logging.getLogger("pitune.gateway.opcua")
BULK_CHUNK = 10_000
"""Loops per ``POST /loops/bulk`` (a small request each, well under the API's limit)."""


def registration_bodies(site: SiteMap, loops: list[LoopRuntime]) -> list[dict]:
    """``POST /loops`` bodies of the loops with a ``registration``, at the block's gains."""
    bodies = []
    for lr in loops:
        reg = lr.cfg.registration
        gains = lr.in_force()
        if reg is None:
            continue
        if gains is None:
            log.error("%s: gains unreadable, not registered", lr.cfg.id)
            continue
        body = {
            "id": lr.cfg.id,
            "kp": gains[0],
            "ki": gains[1],
            "sample_period_s": reg.sample_period_s or lr.cfg.sampling_interval_ms / 1000.0,
            "scaling": reg.scaling.model_dump(exclude_none=True),
            **reg.extra,
        }
        if site.bus.gateway_id is not None:
            body["gateway"] = site.bus.gateway_id
        bodies.append(body)
    return bodies


def register_loops(site: SiteMap, bodies: list[dict]) -> int:
    """``POST /loops/bulk``; if some ids are taken, each loop alone (409: already known,
    unless another gateway's loop took the id: a RegistrationError). Retries while the
    tuner may be starting, for ``timeout_s``. Returns how many were new."""
    url = site.tuner.register_url
    token = os.environ.get(site.tuner.token_env)
    new = 0
    with TunerApi(url, token, timeout=site.tuner.timeout_s, token_env=site.tuner.token_env) as api:
        for start in range(0, len(bodies), BULK_CHUNK):
            chunk = bodies[start : start + BULK_CHUNK]
            r = api.call("POST", "/loops/bulk", what="bulk registration", json=chunk)
            if r.status_code == 409:
                for body in chunk:
                    what = f"registering {body['id']}"
                    one = api.call("POST", "/loops", what=what, json=body)
                    if one.status_code not in (201, 409):
                        raise RegistrationError(f"{what}: HTTP {one.status_code} {one.text[:300]}")
                    if one.status_code == 409:
                        check_not_foreign(one, body["id"], body.get("gateway"))
                    new += one.status_code == 201
            elif not r.is_success:
                raise RegistrationError(f"bulk registration: HTTP {r.status_code} {r.text[:300]}")
            else:
                new += len(chunk)
    log.warning("registered %d new loops with %s (%d known)", new, url, len(bodies) - new)
    return new
