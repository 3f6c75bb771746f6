"""A loop page's live data: its fast-changing figures and the recent samples and gains,
once (``/recent``) or as server-sent events (``/stream``). Reads are open like the REST
GETs; the engine's lock is held only to copy one row of the table."""

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


def _known(tuner, loop_id: str) -> None:
    if loop_id not in tuner.table.slot_of:
        raise HTTPException(404, f"unknown loop {loop_id!r}")


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


@router.get("/api/loops/{loop_id}/recent")
def looprecent_of(loop_id: str, request: Request, n: Count = 0, gn: Count = 0) -> JSONResponse:
    """The loop's recent samples and gains from the ring (after ``n`` / ``gn``)."""
    tuner = tuner_of(request)
    _known(tuner, loop_id)
    recent = recent_of(tuner)
    data = recent.since(loop_id, n, gn) if recent is not None else None
    return JSONResponse({"recent": data, "live": _live(tuner, loop_id)})


def _tick(tuner, loop_id: str, n: int, gn: int) -> dict | None:
    live = _live(tuner, loop_id)
    if live is None:
        return None
    recent = recent_of(tuner)
    data = recent.since(loop_id, n, gn) if recent is not None else None
    return {"live": live, "recent": data}


@router.get("/api/loops/{loop_id}/stream")
async def loop_stream(loop_id: str, request: Request, n: Count = 0, gn: Count = 0):
    """Server-sent events: the loop's new samples and gains, and its live figures, at
    most every STREAM_TICK_S while something changed (a comment every 15 s otherwise)."""
    tuner = tuner_of(request)
    _known(tuner, loop_id)
    last_id = request.headers.get("last-event-id", "")
    if re.fullmatch(r"\d+\.\d+", last_id):  # a reconnect: go on where it left off
        n, gn = (int(x) for x in last_id.split("."))

    async def events():
        nonlocal n, gn
        end = time.monotonic() + STREAM_MAX_S
        quiet_since = time.monotonic()
        previous = None
        yield "retry: 2000\n\n"
        while True:
            if time.monotonic() >= end or not tuner.alive:
                yield f"id: {n}.{gn}\nevent: bye\ndata: {{}}\n\n"
                return
            if await request.is_disconnected():
                return
            data = await asyncio.to_thread(_tick, tuner, loop_id, n, gn)
            if data is None:
                yield "event: gone\ndata: {}\n\n"
                return
            rec = data["recent"]
            fresh = rec is not None and (rec["n"] != n or rec["gn"] != gn)
            if fresh or data["live"] != previous:
                if rec is not None:
                    n, gn = rec["n"], rec["gn"]
                previous = data["live"]
                quiet_since = time.monotonic()
                yield f"id: {n}.{gn}\ndata: {json.dumps(data, allow_nan=False)}\n\n"
            elif time.monotonic() - quiet_since > 15.0:
                quiet_since = time.monotonic()
                yield ": keep-alive\n\n"
            await asyncio.sleep(STREAM_TICK_S)

    headers = {"Cache-Control": "no-store", "X-Accel-Buffering": "no"}
    return StreamingResponse(events(), media_type="text/event-stream", headers=headers)
