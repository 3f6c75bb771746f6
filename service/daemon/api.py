"""The admin API (FastAPI): register, inspect, tune and reset loops; health and metrics.

The app's lifespan owns the :class:`~service.daemon.tuner.Tuner`: it starts with the app and
is stopped (bus closed, state snapshotted) when the server shuts down. Handlers are
plain ``def`` functions: they take the loop table's lock, so they run in the thread
pool rather than on the event loop.

The API documentation needs no internet: ``/docs`` is a page rendered here from the
OpenAPI document (no script, no style sheet, nothing from a CDN: plant networks are
isolated), ``/openapi.json`` is the document itself for any OpenAPI viewer; FastAPI's
Swagger UI and ReDoc pages, which load their code from a CDN, are off.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import gc
import html
import io
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Annotated

from fastapi import (
    APIRouter,
    BackgroundTasks,
    Body,
    FastAPI,
    HTTPException,
    Path,
    Query,
    Request,
    Response,
)
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST

from service.agent.model import Agent
from service.daemon import console, forward, hold_api
from service.daemon.admin import Conflict, OwnedElsewhere, StoreUnavailable, UnknownLoop
from service.daemon.deps import TunerDep, actor_of, admin_event, mutating
from service.daemon.gate import (
    BODY_BYTES,
    BULK_BODY_BYTES,
    Failures,
    Gate,
    is_loopback,
    registering_gateway,
)
from service.daemon.logs import StatusWatch, table_statuses
from service.daemon.schemas import (
    MAX_BULK,
    MAX_PAGE,
    BulkRegistered,
    Health,
    HistoryPage,
    LoopsPage,
    Taken,
)
from service.daemon.settings import Settings
from service.daemon.tuner import Tuner
from service.engine.config import LoopView, Registration
from service.engine.figures import Performance
from service.engine.patch import LoopPatch

log = logging.getLogger("pitune.api")
loops = APIRouter(prefix="/loops", tags=["loops"])
MAX_OFFSET = 2**53
"""Largest page offset: the largest integer a JSON number carries exactly, far beyond
any table; larger ones (which overflowed SQLite's 64-bit integers: 500) are a 422."""
STATUS_CHECK_S = 5.0
"""Seconds between two checks of the loops' statuses for the log (and of the ends of
rejection bursts)."""
Offset = Annotated[int, Query(ge=0, le=MAX_OFFSET)]
Limit = Annotated[int, Query(ge=1, le=MAX_PAGE)]


@loops.post("", status_code=201, dependencies=mutating, responses={409: {"model": Taken}})
def register_loop(config: Registration, tuner: TunerDep, request: Request) -> LoopView:
    """Register a loop; it starts at its registered gains with a fresh agent state."""
    _own_gateway(request, [config])
    view = tuner.register(config, actor=actor_of(request))
    admin_event(tuner, request, "registered", "loop %r registered (%s, kp=%.6g ki=%.6g, seq %d)",
           config.id, view.mode, view.kp, view.ki, view.seq)  # fmt: skip
    return view


@loops.post("/bulk", status_code=201, dependencies=mutating, responses={409: {"model": Taken}},
            max_body_size=BULK_BODY_BYTES)  # fmt: skip
def register_loops(
    configs: Annotated[list[Registration], Body(min_length=1, max_length=MAX_BULK)],
    tuner: TunerDep,
    request: Request,
    after: BackgroundTasks,
) -> BulkRegistered:
    """Register many loops in one call (a large site), all or none: 409 if any id is taken,
    422 if the request names one twice."""
    _own_gateway(request, configs)
    try:
        ids = tuner.register_many(configs, actor=actor_of(request))
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    after.add_task(release_memory)  # once the request's parsed configs are gone
    first = ", ".join(repr(i) for i in ids[:5]) + (", ..." if len(ids) > 5 else "")
    admin_event(tuner, request, "registered", "%d loops registered in bulk: %s", len(ids), first)
    return BulkRegistered(registered=ids)


def _own_gateway(request: Request, configs: list[Registration]) -> None:
    """With a gateway's token, every loop must be that gateway's (403, nothing done)."""
    gateway = registering_gateway(request.scope)
    others = sorted({c.id for c in configs if c.gateway != gateway}) if gateway else []
    if others:
        raise HTTPException(
            403, f"gateway {gateway!r}'s token registers only its own loops, not {others[:5]}"
        )


@loops.get("")
def list_loops(tuner: TunerDep, offset: Offset = 0, limit: Limit = 100) -> LoopsPage:
    """A page of the registered loops, in registration order."""
    return tuner.views(offset, limit)


@loops.get("/{loop_id}", responses={404: {}})
def get_loop(loop_id: str, tuner: TunerDep) -> LoopView:
    """Config, gains, mode, status, last sample time and counters."""
    return tuner.view(loop_id)


@loops.patch("/{loop_id}", dependencies=mutating, responses={404: {}, 422: {}})
def patch_loop(loop_id: str, patch: LoopPatch, tuner: TunerDep, request: Request) -> LoopView:
    """Change the mode, forgetting factor or safety limits."""
    try:
        view = tuner.patch(loop_id, patch)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    admin_event(tuner, request, "patched", "loop %r config changed: %s",
           loop_id, patch.model_dump_json(exclude_unset=True))  # fmt: skip
    return view


@loops.post("/{loop_id}/reset", dependencies=mutating, responses={404: {}})
def reset_loop(loop_id: str, tuner: TunerDep, request: Request) -> LoopView:
    """Zero hidden state and integral, and the registered gains published (a frozen loop:
    the agent state only, its gains are left alone)."""
    view = tuner.reset(loop_id)
    admin_event(tuner, request, "reset", "loop %r reset (kp=%.6g ki=%.6g, seq %d)",
           loop_id, view.kp, view.ki, view.seq)  # fmt: skip
    return view


@loops.delete("/{loop_id}", status_code=204, dependencies=mutating, responses={404: {}})
def delete_loop(loop_id: str, tuner: TunerDep, request: Request) -> None:
    """Unregister a loop; its audit log is kept."""
    tuner.delete(loop_id, actor=actor_of(request))
    admin_event(tuner, request, "deleted", "loop %r deleted", loop_id)


@loops.get("/{loop_id}/history", responses={404: {}})
def loop_history(
    loop_id: str,
    tuner: TunerDep,
    offset: Offset = 0,
    limit: Limit = 100,
) -> HistoryPage:
    """The loop's audit log, newest first."""
    return tuner.history(loop_id, offset, limit)


@loops.get("/{loop_id}/history.jsonl", response_class=Response, responses={404: {}})
def loop_history_jsonl(loop_id: str, tuner: TunerDep, since_id: Offset = 0) -> Response:
    """The loop's audit log, oldest first, as JSON lines (to archive before retention
    prunes it; ``since_id``: only rows after this audit id)."""
    buf = io.BytesIO()
    if not tuner.store.export(buf, loop_id, since_id) and loop_id not in tuner.loop_ids():
        raise HTTPException(404, "unknown loop")
    return Response(buf.getvalue(), media_type="application/x-ndjson")


@loops.post("/{loop_id}/identify", dependencies=mutating, responses={404: {}, 503: {}})
def identify_loop(loop_id: str, tuner: TunerDep, request: Request) -> LoopView:
    """Identify the loop's model again from its closed-loop data (drops the identified
    scaling; a loop registered without a hint stops tuning until it is confident; the
    models refuted on it, whose tuning rang, may be used again)."""
    view = tuner.identify(loop_id, actor=actor_of(request))
    admin_event(tuner, request, "identify", "loop %r: identification restarted", loop_id)
    return view


@loops.get("/{loop_id}/performance", responses={404: {}})
def loop_performance(loop_id: str, tuner: TunerDep) -> Performance:
    """Performance figures: the last setpoint response, recent ones (newest first), the
    window figures (error variance, oscillation, manual, saturated, rejected) and the
    verification state (last-good gains, pending change)."""
    return tuner.performance(loop_id)


@loops.post("/{loop_id}/rollback", dependencies=mutating, responses={404: {}, 409: {}, 503: {}})
def rollback_loop(loop_id: str, tuner: TunerDep, request: Request) -> LoopView:
    """Restore the last-good gains: published in auto, proposed in advisory (409 when the
    gains in force are the last-good ones, or the loop is shadow or frozen)."""
    view = tuner.rollback(loop_id)
    admin_event(tuner, request, "rollback", "loop %r rolled back (kp=%.6g ki=%.6g, seq %d)",
           loop_id, view.kp, view.ki, view.seq)  # fmt: skip
    return view


ProposalSeq = Annotated[int, Path(ge=1, le=MAX_OFFSET)]


@loops.post(
    "/{loop_id}/proposals/{seq}/accept", dependencies=mutating,
    responses={404: {}, 409: {}, 503: {}},
)  # fmt: skip
def accept_proposal(loop_id: str, seq: ProposalSeq, tuner: TunerDep, request: Request) -> LoopView:
    """Accept an advisory loop's pending proposal (its seq in the loop view): sent to the
    gateway as an ``auto`` gains message (reason ``accepted``) and verified like any
    change. 409 if it is not the pending proposal, or may not be accepted now (the
    detail says why: the loop oscillated since it was made, a model identified since is
    out of the envelope or mismatches the hint, or the gains in force moved away from it)."""
    view = tuner.accept(loop_id, seq)
    admin_event(tuner, request, "accepted", "loop %r: proposal %d accepted (kp=%.6g ki=%.6g)",
           loop_id, seq, view.kp, view.ki)  # fmt: skip
    return view


@loops.post(
    "/{loop_id}/proposals/{seq}/reject", dependencies=mutating,
    responses={404: {}, 409: {}, 503: {}},
)  # fmt: skip
def reject_proposal(loop_id: str, seq: ProposalSeq, tuner: TunerDep, request: Request) -> LoopView:
    """Reject an advisory loop's pending proposal: recorded; the agent's proposals start
    again from the gains in force after the cool-down."""
    view = tuner.reject(loop_id, seq)
    admin_event(tuner, request, "rejected", "loop %r: proposal %d rejected", loop_id, seq)
    return view


def release_memory() -> None:
    """Give the memory of a large request back to the system: its parsed models are freed,
    but the allocator keeps their pages (a 9,000-loop bulk registration left ~2 KB per
    loop behind) until asked (glibc's malloc_trim; elsewhere nothing to do)."""
    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


ops = APIRouter(tags=["operations"])


@ops.get("/healthz", responses={503: {"model": Health}})
def healthz(tuner: TunerDep) -> Health:
    """Liveness: the worker thread runs and is not stuck; the store commits and writes."""
    if not tuner.alive:
        return _unhealthy("failing", "worker thread not running")
    if tuner.store_failure is not None:
        return _unhealthy("failing", tuner.store_failure)
    stuck = tuner.worker_stuck
    if stuck is not None:
        return _unhealthy("failing", stuck)
    if tuner.write_failure is not None:
        return _unhealthy("failing", tuner.write_failure)
    # still ok (200): a restart fixes neither, the detail says what the operator must
    others = sorted(tuner.bus.other_tuners if tuner.bus else ())
    details = [f"another tuner on this key prefix: {', '.join(others)}"] if others else []
    details += [tuner.retention_failure] if tuner.retention_failure else []
    return Health(status="ok", detail="; ".join(details))


@ops.get("/readyz", responses={503: {"model": Health}})
def readyz(tuner: TunerDep) -> Health:
    """Readiness: worker running, Zenoh session open, store committing. Cut off from the
    bus after having been connected is "disconnected" (the link went), not "starting"."""
    if not tuner.alive:
        return _unhealthy("starting", "worker not up")
    if not tuner.bus_ready:
        state = "disconnected" if tuner.bus is not None and tuner.bus.was_connected else "starting"
        return _unhealthy(state, "bus not connected: no router or peer")
    if tuner.store_failure is not None:
        return _unhealthy("failing", tuner.store_failure)
    return Health(status="ok")


@ops.get(
    "/metrics", response_class=Response, responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}}
)
def metrics(tuner: TunerDep) -> Response:
    """Prometheus exposition (the loops' status and monitor gauges as last computed
    while the worker holds the loop table, see :meth:`Tuner.refresh_status_counts`)."""
    tuner.refresh_status_counts()
    return Response(tuner.metrics.render(), media_type=CONTENT_TYPE_LATEST)


def _unhealthy(state: str, detail: str) -> JSONResponse:
    return JSONResponse(Health(status=state, detail=detail).model_dump(), status_code=503)


MIN_TOKEN_CHARS = 16
"""A shorter API token is warned about at start-up (guessable: the gate locks a guessing
client out for a minute after 10 tries, which slows a search, not stops it)."""


def _warn_if_open(settings: Settings) -> None:
    token = settings.api_token
    named = [("the API token", token)] if token is not None else []
    gateways = settings.api_gateway_tokens
    named += [(f"the API token of gateway {g!r}", t) for g, t in gateways.items()]
    for name, secret in named:
        chars = len(secret.get_secret_value())
        if chars < MIN_TOKEN_CHARS:
            log.warning(
                "%s has %d characters: guessable. Use a long random one "
                "(openssl rand -hex 32).",
                name, chars,
            )  # fmt: skip
    if token is None and settings.api_gateway_tokens:
        log.warning(
            "gateway tokens are set but no admin token (PITUNE_API_TOKEN): the API is open, "
            "any token may make any change, a gateway's too"
        )
    if token is None and not is_loopback(settings.api_host):
        log.warning(
            "the admin API listens on %r WITHOUT A TOKEN: anyone who reaches it can register, "
            "retune, reset and delete loops. Set PITUNE_API_TOKEN.",
            settings.api_host,
        )


def _check_statuses(tuner: Tuner, watch: StatusWatch) -> None:
    """Log status changes of the loops and the ends of rejection bursts."""
    with tuner.table.lock:
        ids, codes = table_statuses(tuner.table, tuner.clock.wall())
    watch.check(ids, codes)
    tuner.metrics.flush_logs()


async def _watch_statuses(tuner: Tuner, interval_s: float) -> None:
    watch = StatusWatch(tuner.metrics.events)
    while True:
        try:
            await asyncio.to_thread(_check_statuses, tuner, watch)
        except Exception:  # never let the log's watcher take the API down
            log.exception("status check failed")
        await asyncio.sleep(interval_s)


def _docs_page(app: FastAPI) -> str:
    """The API's reference as plain HTML, from its OpenAPI document."""
    spec = app.openapi()
    e = html.escape
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>{e(spec['info']['title'])}</title></head><body>",
        f"<h1>{e(spec['info']['title'])} (API {e(spec['info']['version'])})</h1>",
        f"<p>{e(spec['info'].get('summary', ''))}</p>",
        "<p>Machine-readable: <a href='openapi.json'>openapi.json</a> (OpenAPI "
        f"{e(spec['openapi'])}; load it into any OpenAPI viewer).</p>",
    ]
    for path, methods in spec["paths"].items():
        for method, op in methods.items():
            parts.append(f"<h2><code>{e(method.upper())} {e(path)}</code></h2>")
            parts.append(f"<p>{e(op.get('description') or op.get('summary') or '')}</p>")
            params = op.get("parameters", [])
            if params:
                items = "".join(
                    f"<li><code>{e(p['name'])}</code> ({e(p['in'])}"
                    f"{', required' if p.get('required') else ''}): "
                    f"<code>{e(str(p.get('schema', {})))}</code></li>"
                    for p in params
                )
                parts.append(f"<ul>{items}</ul>")
            body = op.get("requestBody", {}).get("content", {}).get("application/json")
            if body:
                parts.append(f"<p>Body: <code>{e(str(body.get('schema', {})))}</code></p>")
            codes = ", ".join(e(code) for code in op.get("responses", {}))
            parts.append(f"<p>Responses: {codes}</p>")
    parts.append("</body></html>")
    return "".join(parts)


def create_app(
    settings: Settings, agent: Agent | None = None, tuner: Tuner | None = None
) -> FastAPI:
    """The admin API with a tuner owned by its lifespan (``agent``: override, for tests).

    ``tuner``: one already started (``pitune tuner`` starts it before the server, so a
    start-up failure is reported in one line); the lifespan stops it at shutdown."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        _warn_if_open(settings)
        owned = tuner if tuner is not None else Tuner(settings, agent).start()
        app.state.tuner = owned
        watcher = asyncio.create_task(_watch_statuses(owned, STATUS_CHECK_S))
        try:
            yield
        finally:
            watcher.cancel()
            owned.stop()

    app = FastAPI(
        title="pitune tuner",
        summary="Online PI tuning with a meta-RL agent over Zenoh: admin API.",
        version="1",
        lifespan=lifespan,
        docs_url=None,  # Swagger UI and ReDoc load their code from a CDN
        redoc_url=None,
        max_body_size=BODY_BYTES,  # 413 beyond (service.daemon.gate)
    )
    app.state.settings = settings
    app.include_router(loops)
    app.include_router(ops)
    app.include_router(hold_api.router)  # the plant-wide hold at /hold
    app.include_router(console.router)  # the operator console at /ui (docs/console.md)
    forward.install(app)  # a cluster's members answer for each other's loops
    app.state.token_failures = Failures()  # (the console's login counts its own too)
    app.add_middleware(Gate, settings=settings, failures=app.state.token_failures)

    @app.get("/docs", include_in_schema=False, response_class=HTMLResponse)
    def docs() -> HTMLResponse:
        return HTMLResponse(_docs_page(app))

    @app.exception_handler(UnknownLoop)
    async def unknown_loop(request: Request, exc: UnknownLoop) -> JSONResponse:
        return JSONResponse({"detail": f"unknown loop {exc.args[0]!r}"}, status_code=404)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        # Without the offending input: it may be NaN or Infinity, which JSON cannot carry.
        errors = [{k: e[k] for k in ("loc", "msg", "type")} for e in exc.errors()]
        return JSONResponse({"detail": errors}, status_code=422)

    @app.exception_handler(OwnedElsewhere)
    async def owned_elsewhere(request: Request, exc: OwnedElsewhere) -> JSONResponse:
        detail = f"loop {exc.args[0]!r} belongs to another member of the cluster; retry"
        return JSONResponse({"detail": detail}, status_code=503, headers={"Retry-After": "1"})

    @app.exception_handler(StoreUnavailable)
    async def store_unavailable(request: Request, exc: StoreUnavailable) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=503)

    @app.exception_handler(Conflict)
    async def conflict(request: Request, exc: Conflict) -> JSONResponse:
        if exc.gateways:  # a registration's taken ids
            return JSONResponse(Taken(detail=str(exc), gateways=exc.gateways).model_dump(), 409)
        return JSONResponse({"detail": str(exc)}, status_code=409)

    return app
