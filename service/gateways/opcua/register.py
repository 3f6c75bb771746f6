"""The gateway's bulk registration of its loops with the tuner (the map's ``[tuner]``),
made once the gains in force are known, before sampling starts; with the gateway's own
samples key, the check that the tuner has every loop of the map registered with it."""

from __future__ import annotations

import logging
import os

import httpx

from service.gateways.opcua.loops import LoopRuntime
from service.gateways.opcua.sitemap import SiteMap
from service.gateways.registration import RegistrationError, TunerApi, check_not_foreign
from service.wire.protocol import Keys

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
    """``POST /loops/bulk`` (see :func:`prepare`); how many loops were new."""
    with _api(site) as api:
        return len(_register(api, bodies)[0])


def prepare(site: SiteMap, loops: list[LoopRuntime]) -> None:
    """At start, once the gains in force are known: register the map's loops that have a
    ``registration``; then, when the samples go on the gateway's key
    (``bus.samples_gateway``), check that the tuner has every loop of the map registered
    with that gateway (:func:`check_gateway_key`)."""
    bodies = registration_bodies(site, loops)
    with _api(site) as api:
        new, known = _register(api, bodies) if bodies else (set(), {})
        if site.bus.samples_gateway is not None:  # the new ones are: registered with it
            rest = [lr.cfg.id for lr in loops if lr.cfg.id not in new]
            check_gateway_key(site, api, rest, known)


def _api(site: SiteMap) -> TunerApi:
    token = os.environ.get(site.tuner.token_env)
    return TunerApi(site.tuner.register_url, token, timeout=site.tuner.timeout_s,
                    token_env=site.tuner.token_env)  # fmt: skip


def _register(api: TunerApi, bodies: list[dict]) -> tuple[set[str], dict[str, str | None]]:
    """Registers ``bodies`` in chunks; if some ids are taken, each loop alone (409: already
    known, unless another gateway's loop took the id: a RegistrationError). Retries while
    the tuner may be starting, for ``timeout_s``. Returns the ids registered now, and the
    gateway of each loop known already, as its 409 named it."""
    new: set[str] = set()
    known: dict[str, str | None] = {}
    for start in range(0, len(bodies), BULK_CHUNK):
        chunk = bodies[start : start + BULK_CHUNK]
        r = api.call("POST", "/loops/bulk", what="bulk registration", json=chunk)
        if r.status_code == 409:
            for body in chunk:
                what = f"registering {body['id']}"
                one = api.call("POST", "/loops", what=what, json=body)
                if one.status_code == 201:
                    new.add(body["id"])
                elif one.status_code == 409:
                    check_not_foreign(one, body["id"], body.get("gateway"))
                    known.update(_taken(one, body["id"]))
                else:
                    raise RegistrationError(f"{what}: HTTP {one.status_code} {one.text[:300]}")
        elif not r.is_success:
            raise RegistrationError(f"bulk registration: HTTP {r.status_code} {r.text[:300]}")
        else:
            new.update(body["id"] for body in chunk)
    log.warning("registered %d new loops with %s (%d known)", len(new), api.url,
                len(bodies) - len(new))  # fmt: skip
    return new, known


def _taken(response: httpx.Response, loop_id: str) -> dict[str, str | None]:
    """``{loop_id: its gateway}`` from a 409's ``gateways``; empty if it does not say (not
    the tuner's JSON: a proxy's page), then :func:`check_gateway_key` asks."""
    try:
        taken = response.json().get("gateways")
    except (ValueError, AttributeError):
        return {}
    return {loop_id: taken[loop_id]} if isinstance(taken, dict) and loop_id in taken else {}


def check_gateway_key(
    site: SiteMap, api: TunerApi, loop_ids: list[str], known: dict[str, str | None]
) -> None:
    """Raise a :class:`RegistrationError` if a loop of ``loop_ids`` is registered with
    another gateway than the one whose samples key the gateway publishes on, or with none
    (``known``: what a 409 said; the others are read, ``GET /loops/{id}``): the tuner
    would reject every sample of it there (``wrong_gateway``) and never tune it. A loop
    not registered at all is logged: its samples are rejected (``unknown_loop``) until
    someone registers it, which must be with this gateway's id."""
    gateway = site.bus.samples_gateway
    wrong: dict[str, str | None] = {}
    missing: list[str] = []
    for loop_id in loop_ids:
        if loop_id in known:
            found = known[loop_id]
        else:
            what = f"reading loop {loop_id}"
            r = api.call("GET", f"/loops/{loop_id}", what=what)
            if r.status_code == 404:
                missing.append(loop_id)
                continue
            found = _gateway_in(r, what)
        if found != gateway:
            wrong[loop_id] = found
    if missing:
        log.warning(
            "%d loop(s) of the map not registered with the tuner (%s): their samples are "
            "rejected (unknown_loop) until they are, with \"gateway\": %r", len(missing),
            _first(missing), gateway,
        )  # fmt: skip
    if wrong:
        named = _first([f"{i} ({'no gateway' if g is None else f'gateway {g!r}'})"
                        for i, g in wrong.items()])  # fmt: skip
        raise RegistrationError(
            f"{len(wrong)} loop(s) of the map registered without this gateway's id "
            f"{gateway!r}: {named}. The gateway publishes the samples on "
            f"{Keys(site.bus.prefix).gateway_samples(gateway)}, where the tuner rejects "
            "theirs (wrong_gateway): they would never be tuned. Register them with "
            f'"gateway": "{gateway}" (delete them, DELETE /loops/{{id}}, and register '
            "again), or set shared_samples_key = true in [bus] to publish on "
            f"{Keys(site.bus.prefix).batch} (a per-gateway Zenoh user may not: "
            "docs/opcua.md, The gateway's samples key)"
        )


def _gateway_in(response: httpx.Response, what: str) -> str | None:
    """The gateway of the loop a ``GET /loops/{id}`` answered."""
    try:
        if response.is_success:
            return response.json()["config"].get("gateway")
    except (ValueError, KeyError, TypeError, AttributeError):
        pass  # not the tuner's JSON (a proxy's page): said below
    raise RegistrationError(f"{what}: HTTP {response.status_code} {response.text[:300]}")


def _first(items: list[str], n: int = 5) -> str:
    return ", ".join(items[:n]) + (f", ... ({len(items)} in all)" if len(items) > n else "")
