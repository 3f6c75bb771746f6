"""The console's live data as server-sent events: a loop page's fast-changing figures,
recent samples and gains and the plant-wide hold, once (``/recent``) or as a stream
(``/stream``); every other page's plant-wide hold (``/api/hold/stream``). Reads are open
like the REST GETs; the engine's lock is held only to copy one row of the table."""

from __future__ import annotations

import asyncio
import json
import re
import time
from typing import Annotated

import numpy as np
from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import JSONResponse, StreamingResponse

from service.daemon.console.context import MODES, STATUS_NAMES, finite, recent_of, tuner_of
from service.engine import status, views
from service.engine.status import STATUSES

router = APIRouter()

Count = Annotated[int, Query(ge=0, description="Samples (n) or gains (gn) already seen.")]

STREAM_TICK_S = 0.5
"""How often a loop page's stream looks for new samples."""
STREAM_MAX_S = 4.0
"""A stream ends after this long (event ``bye``) and the page opens the next one where it
left off: the server's graceful shutdown, which waits for open responses, is never held
up longer than this by an open console."""


def _unknown(loop_id: str) -> HTTPException:
    return HTTPException(404, f"unknown loop {loop_id!r}")


def _live(tuner, loop_id: str) -> dict | None:
    """The loop's fast-changing figures (no config parsing), None if it is gone."""
    tb = tuner.table
    wall = time.time()
    with tuner.engine.lock:
        s = tb.slot_of.get(loop_id)
        if s is None:
            return None
        code = int(tb.statuses(np.array([s]), wall)[0])
        return {
            "status": STATUS_NAMES[code],
            "status_why": status.why(tb, s, STATUSES[code], wall),
            "mode": MODES[int(tb.mode[s])].value,
            "kp": float(tb.kp[s]),
            "ki": float(tb.ki[s]),
            "seq": int(tb.seq[s]),
            "last_sample_t": finite(tb.last_t[s]),
            "samples": int(tb.n_samples[s]),
            "steps": int(tb.n_steps[s]),
            "updates": int(tb.n_updates[s]),
            "rejected": int(tb.n_rejected[s]),
            "quiet": int(tb.n_quiet[s]),
            # what the status may not say: a hold of the agent, an oscillation
            "hold": None if (hold := views.hold(tb, s)) is None else hold.model_dump(),
            "oscillating": bool(tb.o_osc[s]),
        }


def _plant(tuner) -> dict:
    """The plant-wide hold (``GET /hold``): every page's banner."""
    return tuner.hold.model_dump()


def _tick(tuner, loop_id: str, n: int, gn: int) -> dict | None:
    """A loop page's data: its live figures, its samples and gains from the ring (after
    ``n`` / ``gn``), the plant-wide hold; None if the loop is gone."""
    live = _live(tuner, loop_id)
    if live is None:
        return None
    recent = recent_of(tuner)
    data = recent.since(loop_id, n, gn) if recent is not None else None
    return {"live": live, "recent": data, "plant": _plant(tuner)}


@router.get("/api/loops/{loop_id}/recent")
def looprecent_of(loop_id: str, request: Request, n: Count = 0, gn: Count = 0) -> JSONResponse:
    """The loop page's data once (:func:`_tick`)."""
    data = _tick(tuner_of(request), loop_id, n, gn)
    if data is None:
        raise _unknown(loop_id)
    return JSONResponse(data)


def _events(request: Request, tuner, read, event_id=lambda: None) -> StreamingResponse:
    """Server-sent events of ``read()`` (called in a thread every STREAM_TICK_S): it
    answers None when its subject is gone (event ``gone``), else ``(seen, data)``:
    ``data`` is sent, with the id ``event_id()`` (None: none), when ``seen`` differs
    from the last sent (a comment every 15 s otherwise). The stream ends after
    STREAM_MAX_S (event ``bye``, with the id) and the page opens the next."""

    async def events():
        end = time.monotonic() + STREAM_MAX_S
        quiet_since = time.monotonic()
        previous = None
        yield "retry: 2000\n\n"
        while True:
            if time.monotonic() >= end or not tuner.alive:
                yield f"{_id_line(event_id())}event: bye\ndata: {{}}\n\n"
                return
            if await request.is_disconnected():
                return
            read_now = await asyncio.to_thread(read)
            if read_now is None:
                yield "event: gone\ndata: {}\n\n"
                return
            seen, data = read_now
            if seen != previous:
                previous = seen
                quiet_since = time.monotonic()
                yield f"{_id_line(event_id())}data: {json.dumps(data, allow_nan=False)}\n\n"
            elif time.monotonic() - quiet_since > 15.0:
                quiet_since = time.monotonic()
                yield ": keep-alive\n\n"
            await asyncio.sleep(STREAM_TICK_S)

    headers = {"Cache-Control": "no-store", "X-Accel-Buffering": "no"}
    return StreamingResponse(events(), media_type="text/event-stream", headers=headers)


def _id_line(event_id: str | None) -> str:
    return "" if event_id is None else f"id: {event_id}\n"


@router.get("/api/loops/{loop_id}/stream")
async def loop_stream(loop_id: str, request: Request, n: Count = 0, gn: Count = 0):
    """Server-sent events: the loop's new samples and gains, its live figures and the
    plant-wide hold, at most every STREAM_TICK_S while something changed."""
    tuner = tuner_of(request)
    if loop_id not in tuner.table.slot_of:
        raise _unknown(loop_id)
    last_id = request.headers.get("last-event-id", "")
    if re.fullmatch(r"\d+\.\d+", last_id):  # a reconnect: go on where it left off
        n, gn = (int(x) for x in last_id.split("."))

    def read():
        nonlocal n, gn
        data = _tick(tuner, loop_id, n, gn)
        if data is None:
            return None
        if (rec := data["recent"]) is not None:  # new samples or gains: new n, gn, sent
            n, gn = rec["n"], rec["gn"]
        return (n, gn, data["live"], data["plant"]), data

    return _events(request, tuner, read, lambda: f"{n}.{gn}")


@router.get("/api/hold/stream")
async def hold_stream(request: Request):
    """Server-sent events: the plant-wide hold, at once and at each change (every page
    but a loop's, whose own stream carries it, shows it in its banner)."""
    tuner = tuner_of(request)

    def read():
        plant = _plant(tuner)
        return plant, plant

    return _events(request, tuner, read)
