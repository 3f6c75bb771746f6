"""The admin API (FastAPI): register, inspect, tune and reset loops; health and metrics.

The app's lifespan owns the :class:`~service.daemon.tuner.Tuner`: it starts with the app and
is stopped (bus closed, state snapshotted) when the server shuts down. Handlers are
plain ``def`` functions: they take the loop table's lock, so they run in the thread
pool rather than on the event loop.
"""

from __future__ import annotations

import ipaddress
import logging
import secrets
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Annotated

from fastapi import (
    APIRouter,
    Body,
    Depends,
    FastAPI,
    HTTPException,
    Query,
    Request,
    Response,
    status,
)
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from prometheus_client import CONTENT_TYPE_LATEST

from service.agent.model import Agent
from service.daemon.schemas import (
    MAX_BULK,
    MAX_PAGE,
    BulkRegistered,
    Health,
    HistoryPage,
    LoopsPage,
)
from service.daemon.settings import Settings
from service.daemon.tuner import Conflict, StoreUnavailable, Tuner, UnknownLoop
from service.engine.config import LoopConfig, LoopPatch, LoopView

log = logging.getLogger("pitune.api")
_bearer = HTTPBearer(auto_error=False, description="PITUNE_API_TOKEN, when set")


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_tuner(request: Request) -> Tuner:
    return request.app.state.tuner


def require_token(
    settings: Annotated[Settings, Depends(get_settings)],
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """Mutating calls need the bearer token when one is configured."""
    if settings.api_token is None:
        return
    expected = settings.api_token.get_secret_value().encode()
    given = credentials.credentials.encode() if credentials else b""
    if not secrets.compare_digest(given, expected):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing or invalid bearer token",
            headers={"WWW-Authenticate": "Bearer"},
        )


TunerDep = Annotated[Tuner, Depends(get_tuner)]
loops = APIRouter(prefix="/loops", tags=["loops"])
# Only changes need the token: reads stay open like /healthz and /metrics (the demo and
# dashboards read loops without one); protect reads by binding to loopback or a proxy.
mutating = [Depends(require_token)]
Offset = Annotated[int, Query(ge=0)]
Limit = Annotated[int, Query(ge=1, le=MAX_PAGE)]


@loops.post("", status_code=201, dependencies=mutating, responses={409: {}})
def register_loop(config: LoopConfig, tuner: TunerDep) -> LoopView:
    """Register a loop; it starts at its registered gains with a fresh agent state."""
    return tuner.register(config)


@loops.post("/bulk", status_code=201, dependencies=mutating, responses={409: {}})
def register_loops(
    configs: Annotated[list[LoopConfig], Body(max_length=MAX_BULK)], tuner: TunerDep
) -> BulkRegistered:
    """Register many loops in one call (a large site), all or none: 409 if any id is taken."""
    return BulkRegistered(registered=tuner.register_many(configs))


@loops.get("")
def list_loops(tuner: TunerDep, offset: Offset = 0, limit: Limit = 100) -> LoopsPage:
    """A page of the registered loops, in registration order."""
    return tuner.views(offset, limit)


@loops.get("/{loop_id}", responses={404: {}})
def get_loop(loop_id: str, tuner: TunerDep) -> LoopView:
    """Config, gains, mode, status, last sample time and counters."""
    return tuner.view(loop_id)


@loops.patch("/{loop_id}", dependencies=mutating, responses={404: {}, 422: {}})
def patch_loop(loop_id: str, patch: LoopPatch, tuner: TunerDep) -> LoopView:
    """Change the mode, forgetting factor or safety limits."""
    try:
        return tuner.patch(loop_id, patch)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None


@loops.post("/{loop_id}/reset", dependencies=mutating, responses={404: {}})
def reset_loop(loop_id: str, tuner: TunerDep) -> LoopView:
    """Zero hidden state and integral, and the registered gains published (a frozen loop:
    the agent state only, its gains are left alone)."""
    return tuner.reset(loop_id)


@loops.delete("/{loop_id}", status_code=204, dependencies=mutating, responses={404: {}})
def delete_loop(loop_id: str, tuner: TunerDep) -> None:
    """Unregister a loop; its audit log is kept."""
    tuner.delete(loop_id)


@loops.get("/{loop_id}/history", responses={404: {}})
def loop_history(
    loop_id: str,
    tuner: TunerDep,
    offset: Offset = 0,
    limit: Limit = 100,
) -> HistoryPage:
    """The loop's audit log, newest first."""
    return tuner.history(loop_id, offset, limit)


ops = APIRouter(tags=["operations"])


@ops.get("/healthz", responses={503: {"model": Health}})
def healthz(tuner: TunerDep) -> Health:
    """Liveness: the worker thread runs and the store commits."""
    if not tuner.alive:
        return _unhealthy("failing", "worker thread not running")
    if tuner.store_failure is not None:
        return _unhealthy("failing", tuner.store_failure)
    return Health(status="ok")


@ops.get("/readyz", responses={503: {"model": Health}})
def readyz(tuner: TunerDep) -> Health:
    """Readiness: worker running, Zenoh session open, store committing."""
    if not tuner.ready:
        return _unhealthy("starting", "bus or worker not up")
    if tuner.store_failure is not None:
        return _unhealthy("failing", tuner.store_failure)
    return Health(status="ok")


@ops.get(
    "/metrics", response_class=Response, responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}}
)
def metrics(tuner: TunerDep) -> Response:
    """Prometheus exposition."""
    tuner.refresh_status_counts()
    return Response(tuner.metrics.render(), media_type=CONTENT_TYPE_LATEST)


def _unhealthy(state: str, detail: str) -> JSONResponse:
    return JSONResponse(Health(status=state, detail=detail).model_dump(), status_code=503)


def _warn_if_open(settings: Settings) -> None:
    if settings.api_token is None and not _is_loopback(settings.api_host):
        log.warning(
            "the admin API listens on %r WITHOUT A TOKEN: anyone who reaches it can register, "
            "retune, reset and delete loops. Set PITUNE_API_TOKEN.",
            settings.api_host,
        )


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: it may resolve to anything
        return False


def create_app(settings: Settings, agent: Agent | None = None) -> FastAPI:
    """The admin API with a tuner owned by its lifespan (``agent``: override, for tests)."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        _warn_if_open(settings)
        tuner = Tuner(settings, agent)
        tuner.start()
        app.state.tuner = tuner
        try:
            yield
        finally:
            tuner.stop()

    app = FastAPI(
        title="pitune tuner",
        summary="Online PI tuning with a meta-RL agent over Zenoh: admin API.",
        version="1",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.include_router(loops)
    app.include_router(ops)

    @app.exception_handler(UnknownLoop)
    async def unknown_loop(request: Request, exc: UnknownLoop) -> JSONResponse:
        return JSONResponse({"detail": f"unknown loop {exc.args[0]!r}"}, status_code=404)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        # Without the offending input: it may be NaN or Infinity, which JSON cannot carry.
        errors = [{k: e[k] for k in ("loc", "msg", "type")} for e in exc.errors()]
        return JSONResponse({"detail": errors}, status_code=422)

    @app.exception_handler(StoreUnavailable)
    async def store_unavailable(request: Request, exc: StoreUnavailable) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=503)

    @app.exception_handler(Conflict)
    async def conflict(request: Request, exc: Conflict) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=409)

    return app
