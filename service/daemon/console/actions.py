"""The console's actions on a loop (patch, reset, rollback, decide a proposal) and on the
plant (hold all tuning, release): each needs a console session
(:func:`service.daemon.console.sessions.acting`: cookie, CSRF token, same origin), runs
the tuner's own method as the session's actor and is logged."""

from __future__ import annotations

import asyncio
import inspect
import json
import logging

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import JSONResponse

from service.daemon.console.context import tuner_of
from service.daemon.console.sessions import Session, acting
from service.engine.patch import LoopPatch
from service.engine.plant_hold import HoldRequest

router = APIRouter()


def _accepts(method, name: str) -> bool:
    try:
        return name in inspect.signature(method).parameters
    except (TypeError, ValueError):
        return False


def _log_action(tuner, request: Request, session: Session, what: str) -> None:
    client = request.client.host if request.client else "?"
    tuner.metrics.events.limiter.log(
        logging.INFO, "console", "%s by %s via the console from %s", what, session.actor, client
    )


def _parsed(model, body: bytes):
    """``body`` as the pydantic ``model``; else 422 with every error on one line."""
    try:
        return model.model_validate_json(body)
    except ValueError as exc:
        errors = getattr(exc, "errors", lambda: [])()
        msg = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors)
        raise HTTPException(422, msg or str(exc)) from None


def _jsonable(view) -> dict:
    return json.loads(view.model_dump_json())


@router.post("/api/loops/{loop_id}/patch")
async def patch_loop(loop_id: str, request: Request) -> JSONResponse:
    """PATCH /loops/{id} for a logged-in console (mode, guard limits, ...)."""
    session = acting(request)
    tuner = tuner_of(request)
    patch = _parsed(LoopPatch, await request.body())
    kwargs = {"actor": session.actor} if _accepts(tuner.patch, "actor") else {}
    try:
        view = await asyncio.to_thread(tuner.patch, loop_id, patch, **kwargs)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    except LookupError:
        raise HTTPException(404, f"unknown loop {loop_id!r}") from None
    what = f"loop {loop_id!r} patched {patch.model_dump_json(exclude_unset=True)}"
    _log_action(tuner, request, session, what)
    return JSONResponse(_jsonable(view))


@router.post("/api/loops/{loop_id}/reset")
async def reset_loop(loop_id: str, request: Request) -> JSONResponse:
    return await _act_on(request, loop_id, "reset", lambda tuner: tuner.reset)


@router.post("/api/loops/{loop_id}/rollback")
async def rollback_loop(loop_id: str, request: Request) -> JSONResponse:
    """Back to the last-good gains (auto: published; advisory: proposed)."""
    return await _act_on(request, loop_id, "rolled back", lambda tuner: tuner.rollback)


@router.post("/api/loops/{loop_id}/proposals/{seq}/{decision}")
async def decide_proposal(loop_id: str, seq: int, decision: str, request: Request) -> JSONResponse:
    """Approve (``accept``) or ``reject`` an advisory loop's pending proposal ``seq``."""
    if decision not in ("accept", "reject"):
        raise HTTPException(404, "accept or reject")

    def method(tuner):
        decide = tuner.accept if decision == "accept" else tuner.reject
        return lambda loop_id, **kw: decide(loop_id, seq, **kw)

    return await _act_on(request, loop_id, f"proposal {seq} {decision}ed", method)


@router.post("/api/hold")
async def hold_plant(request: Request) -> JSONResponse:
    """``PUT /hold`` for a logged-in console: hold all tuning, ``{"reason": ...}`` (422:
    what is wrong with it, on one line); already held: the reason replaced."""
    acting(request)  # no session: 401, whatever the body
    reason = _parsed(HoldRequest, await request.body()).reason
    what = f"plant-wide hold set: {reason!r}"
    return await _act(request, what, lambda tuner, actor: tuner.set_hold(reason, actor))


@router.post("/api/hold/release")
async def release_plant(request: Request) -> JSONResponse:
    """``DELETE /hold`` for a logged-in console (not held: nothing changes)."""
    return await _act(request, "plant-wide hold released", lambda t, actor: t.release_hold(actor))


async def _act_on(request: Request, loop_id: str, what: str, method) -> JSONResponse:
    """:func:`_act` with the tuner's ``method(tuner)(loop_id, actor=...)``: 404 for an
    unknown loop."""
    return await _act(
        request, f"loop {loop_id!r} {what}",
        lambda tuner, actor: method(tuner)(loop_id, actor=actor), f"unknown loop {loop_id!r}",
    )  # fmt: skip


async def _act(request: Request, what: str, call, unknown: str = "") -> JSONResponse:
    """Run ``call(tuner, actor)`` for a logged-in console, as its actor, and log ``what``:
    404 ``unknown`` (a LookupError), 409 a conflict (nothing to roll back, a stale
    proposal), 503 store failing."""
    session = acting(request)
    tuner = tuner_of(request)
    try:
        view = await asyncio.to_thread(call, tuner, session.actor)
    except LookupError:
        raise HTTPException(404, unknown) from None
    except Exception as exc:  # StoreUnavailable, Conflict: by name (no import cycle)
        status = {"StoreUnavailable": 503, "Conflict": 409}.get(type(exc).__name__)
        if status is not None:
            raise HTTPException(status, str(exc)) from None
        raise
    _log_action(tuner, request, session, what)
    return JSONResponse(_jsonable(view))
