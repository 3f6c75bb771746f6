"""The operator console's routes: pages, the overview's and the tuner page's JSON, login,
static assets; a loop's live data (:mod:`.stream`) and the actions (:mod:`.actions`) are
included under the same ``/ui`` prefix.

Reads are open like the REST GETs. Every action needs a console session
(:mod:`service.daemon.console.sessions`: cookie, CSRF token, same origin).

Nothing here holds the engine's lock for long: the overview copies a few numpy columns
of the loop table under it (a few ms at 10,000 loops) and filters, sorts and pages
outside it; a loop's page reads the REST views and the ring of recent samples
(:mod:`service.daemon.recent`).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import secrets
import string
import time
import urllib.parse
from functools import cache
from importlib import resources
from typing import Any

import numpy as np
from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import (
    HTMLResponse,
    JSONResponse,
    RedirectResponse,
    Response,
)

from service.daemon.console import actions, stream
from service.daemon.console.assets import asset
from service.daemon.console.context import MODES, STATUS_NAMES, finite, recent_of, tuner_of
from service.daemon.console.sessions import (
    ACTOR_NAME,
    COOKIE,
    LOGIN_PENALTY_S,
    app_state,
    safe_next,
    session_of,
    sessions_of,
)
from service.daemon.console.tuner_view import Rates, tuner_figures
from service.daemon.gate import LOGIN_BODY_BYTES, token_matches
from service.daemon.recent import REASONS
from service.engine import status, steady, verify, views
from service.engine.plant_hold import REASON_CHARS
from service.engine.status import STATUSES
from service.wire.protocol import Mode

log = logging.getLogger("pitune.console")
router = APIRouter(prefix="/ui", include_in_schema=False)

PAGE_MAX = 500
_SORTS = {
    "registered", "id", "status", "mode", "kp", "ki", "last_sample", "last_change",
    "samples", "steps", "updates", "rejected", "rms_e", "gateway",
}  # fmt: skip


# -- helpers ----------------------------------------------------------------------------
@cache
def _template(name: str) -> string.Template:
    text = resources.files(__package__).joinpath("templates", name).read_text("utf-8")
    return string.Template(text)


def _page(request: Request, title: str, body: str, script: str, **values: str) -> HTMLResponse:
    """A console page: the layout around the template ``body``, values HTML-escaped."""
    import html

    session = session_of(request)
    settings = request.app.state.settings
    esc = {k: html.escape(str(v), quote=True) for k, v in values.items()}
    content = _template(body).safe_substitute(esc)
    who = (
        f"<span class='who'>{html.escape(session.actor)}</span>"
        "<form method='post' action='/ui/logout' class='inline'>"
        f"<input type='hidden' name='csrf' value='{html.escape(session.csrf)}'>"
        "<button id='logout' type='submit'>Log out</button></form>"
        if session
        else f"<a id='login-link' href='/ui/login?next={urllib.parse.quote(request.url.path)}'>"
        "Log in</a>"
    )
    page = _template("layout.html").safe_substitute(
        title=html.escape(title),
        content=content,
        who=who,
        csrf=html.escape(session.csrf if session else ""),
        logged_in="1" if session else "",
        # the plant-wide hold's banner: a loop page's own stream carries it
        hold_stream="" if script == "loop.js" else "1",
        open_api="1" if settings.api_token is None else "",
        scripts="".join(
            f"<script src='/ui/static/{html.escape(name)}'></script>"
            for name in (["vendor/uplot/uPlot.iife.min.js"] if script == "loop.js" else [])
            + ["console.js"]
            + ([script] if script else [])
        ),
        styles="<link rel='stylesheet' href='/ui/static/vendor/uplot/uPlot.min.css'>"
        if script == "loop.js"
        else "",
    )
    return HTMLResponse(page, headers=_NO_STORE)


_NO_STORE = {
    "Cache-Control": "no-store",
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "same-origin",
    # uPlot sizes its elements with inline styles: 'unsafe-inline' for styles only
    "Content-Security-Policy": "default-src 'self'; img-src 'self' data:; "
    "style-src 'self' 'unsafe-inline'; script-src 'self'; connect-src 'self'; "
    "frame-ancestors 'none'",
}


# -- pages ------------------------------------------------------------------------------
_MODE_NAMES = " ".join(m.value for m in Mode)
"""The modes a page offers (its data-modes attribute: the mode buttons, the filter)."""


@router.get("", response_class=HTMLResponse)
@router.get("/", response_class=HTMLResponse)
def overview_page(request: Request) -> HTMLResponse:
    return _page(request, "Loops", "overview.html", "overview.js", modes=_MODE_NAMES)


@router.get("/loops/{loop_id}", response_class=HTMLResponse)
def loop_page(loop_id: str, request: Request) -> HTMLResponse:
    tuner = tuner_of(request)
    if loop_id not in tuner.table.slot_of:
        return _page(request, "Unknown loop", "unknown.html", "", loop_id=loop_id)
    return _page(request, loop_id, "loop.html", "loop.js", loop_id=loop_id, modes=_MODE_NAMES)


@router.get("/tuner", response_class=HTMLResponse)
def tuner_page(request: Request) -> HTMLResponse:
    return _page(request, "Tuner", "tuner.html", "tuner.js", reason_chars=str(REASON_CHARS))


LOGIN_ERRORS = {"wrong_token": "Wrong token."}
"""The login page's error texts, by the code a failed login's redirect names: the page
shows no text from its URL (a link to the console's own login page would otherwise show
a phisher's words there); an unknown code shows nothing."""


@router.get("/login", response_class=HTMLResponse)
def login_page(request: Request, next: str = "/ui", error: str = "") -> HTMLResponse:
    text = LOGIN_ERRORS.get(error, "")
    return _page(request, "Log in", "login.html", "", next=safe_next(next), error=text)


@router.post("/login", max_body_size=LOGIN_BODY_BYTES)
async def login(request: Request) -> Response:
    form = urllib.parse.parse_qs((await request.body()).decode("utf-8", "replace"))
    token = form.get("token", [""])[0]
    name = ACTOR_NAME.sub("", form.get("name", [""])[0])[:40]
    target = safe_next(form.get("next", ["/ui"])[0])
    client = request.client.host if request.client else "?"
    failures = request.app.state.token_failures
    locked = failures.lockout(client)  # again: logins may have failed since the gate looked
    if locked is not None:  # (nothing awaits between here and the failure's count)
        raise HTTPException(429, locked[0], headers=locked[1])
    # an open API (no token set): the console is open too (any token logs in)
    if not token_matches(request.app.state.settings, token):
        failures.failed(client, "console login")
        await asyncio.sleep(LOGIN_PENALTY_S)  # slows guessing down
        query = urllib.parse.urlencode({"next": target, "error": "wrong_token"})
        return RedirectResponse(f"/ui/login?{query}", status_code=303)
    actor = f"ui:{name}" if name else "ui"
    sessions = sessions_of(request)
    sessions.drop(request.cookies.get(COOKIE))
    sid, _ = sessions.create(actor)
    log.info("console login of %s from %s", actor, client)
    response = RedirectResponse(target, status_code=303)
    # a browser session's cookie (no max_age): the daemon ends the session after
    # SESSION_IDLE_S without use, which a fixed cookie lifetime from the login would cut
    response.set_cookie(
        COOKIE, sid, httponly=True, samesite="strict", path="/ui",
        secure=request.url.scheme == "https",
    )  # fmt: skip
    return response


@router.post("/logout")
async def logout(request: Request) -> Response:
    session = session_of(request)
    if session is not None:
        form = urllib.parse.parse_qs((await request.body()).decode("utf-8", "replace"))
        given = form.get("csrf", [""])[0] or request.headers.get("x-csrf-token", "")
        if not secrets.compare_digest(given.encode(), session.csrf.encode()):
            raise HTTPException(403, "missing or wrong CSRF token")
        sessions_of(request).drop(request.cookies.get(COOKIE))
    response = RedirectResponse("/ui", status_code=303)
    response.delete_cookie(COOKIE, path="/ui", httponly=True, samesite="strict")
    return response


# -- overview ---------------------------------------------------------------------------
def _columns(tuner) -> dict[str, Any]:
    """The overview's columns of every loop, copied under the engine lock (vectorised)."""
    wall = time.time()
    tb = tuner.table
    with tuner.engine.lock:
        ids = list(tb.slot_of)
        slots = np.fromiter(tb.slot_of.values(), np.int64, len(ids))
        cols = {
            "status": tb.statuses(slots, wall) if len(ids) else np.zeros(0, np.int64),
            "mode": tb.mode[slots],
            "kp": tb.kp[slots],
            "ki": tb.ki[slots],
            "last_sample": tb.last_t[slots],
            "last_wall": tb.last_wall[slots],
            "seq": tb.seq[slots],
            "samples": tb.n_samples[slots],
            "steps": tb.n_steps[slots],
            "updates": tb.n_updates[slots],
            "rejected": tb.n_rejected[slots],
            "quiet": tb.n_quiet[slots],
            "pending": verify.changed(tb, slots),
            "oscillating": tb.o_osc[slots],
            "iae": tb.f_iae[slots],
            "hold": views.holds(tb, slots),
        }
        gateways = [tb.gateways[s] or "" for s in slots.tolist()]
    cols["ids"] = ids
    cols["gateway"] = gateways
    cols["wall"], cols["now"] = wall, steady.now(tb, wall)  # (now: last_wall's clock)
    return cols


def _whys(tuner, ids: list[str], codes: np.ndarray, wall: float) -> list[str | None]:
    """The page's rows' status_why (the status badge's tooltip): one lock for the page's
    rows only (a page is at most PAGE_MAX), None for a loop deleted meanwhile."""
    tb = tuner.table
    with tuner.engine.lock:
        slots = [tb.slot_of.get(i) for i in ids]
        return [
            None if s is None else status.why(tb, s, STATUSES[int(code)], wall)
            for s, code in zip(slots, codes.tolist(), strict=True)
        ]


@router.get("/api/loops")
def overview_data(
    request: Request,
    offset: int = Query(0, ge=0, le=2**53),
    limit: int = Query(100, ge=1, le=PAGE_MAX),
    q: str = Query("", max_length=200),
    status: str = Query("", max_length=400),
    mode: str = Query("", max_length=100),
    sort: str = Query("registered"),
    desc: bool = False,
) -> JSONResponse:
    """A page of loops, filtered (id or gateway containing ``q``, any case; statuses and
    modes comma-separated), sorted, with the counts per status of all loops."""
    started = time.perf_counter()
    tuner = tuner_of(request)
    c = _columns(tuner)
    ids = c["ids"]
    n = len(ids)
    recent = recent_of(tuner)
    summary = recent.summary(ids) if recent is not None and n else None
    keep = np.ones(n, bool)
    if q:
        needle = q.strip().lower()
        gws = c["gateway"]
        keep &= np.fromiter(
            (needle in i.lower() or needle in g.lower() for i, g in zip(ids, gws, strict=True)),
            bool,
            n,
        )
    if status:
        codes = [STATUS_NAMES.index(s) for s in status.split(",") if s in STATUS_NAMES]
        keep &= np.isin(c["status"], codes)
    if mode:
        codes = [i for i, m in enumerate(MODES) if m.value in mode.split(",")]
        keep &= np.isin(c["mode"], codes)
    rows = np.flatnonzero(keep)
    sort = sort if sort in _SORTS else "registered"
    if sort != "registered" and rows.size:
        if sort == "id":
            key = np.array([ids[i] for i in rows.tolist()], dtype=object)
        elif sort == "gateway":
            key = np.array([c["gateway"][i] for i in rows.tolist()], dtype=object)
        elif sort in ("last_change", "rms_e"):
            col = "last_wall" if sort == "last_change" else "rms_e"
            key = (
                np.nan_to_num(summary[col][rows], nan=-np.inf)
                if summary is not None
                else np.zeros(rows.size)
            )
        elif sort == "status":
            key = np.array(STATUS_NAMES, dtype=object)[c["status"][rows]]
        else:
            key = c[sort][rows]
            if key.dtype.kind == "f":
                key = np.nan_to_num(key, nan=-np.inf)
        order = np.argsort(key, kind="stable")
        rows = rows[order[::-1] if desc else order]
    elif desc:
        rows = rows[::-1]
    page = rows[offset : offset + limit]
    whys = _whys(tuner, [ids[i] for i in page.tolist()], c["status"][page], c["wall"])
    items = []
    for i, why in zip(page.tolist(), whys, strict=True):
        last_change = None
        if summary is not None and math.isfinite(summary["last_wall"][i]):
            last_change = {
                "wall": float(summary["last_wall"][i]),
                "reason": REASONS[int(summary["reason"][i])],
                "dkp": finite(summary["dkp"][i]),
                "dki": finite(summary["dki"][i]),
            }
        items.append(
            {
                "id": ids[i],
                "status": STATUS_NAMES[int(c["status"][i])],
                "status_why": why,
                "hold": views.HOLDS[int(c["hold"][i])],
                "mode": MODES[int(c["mode"][i])].value,
                "kp": float(c["kp"][i]),
                "ki": float(c["ki"][i]),
                "seq": int(c["seq"][i]),
                "gateway": c["gateway"][i] or None,
                "last_sample_t": finite(c["last_sample"][i]),
                "last_sample_age_s": finite(c["now"] - c["last_wall"][i])
                if c["samples"][i]
                else None,
                "last_change": last_change,
                "rms_e": finite(summary["rms_e"][i]) if summary is not None else None,
                "verification": {
                    "pending": bool(c["pending"][i]),
                    "oscillating": bool(c["oscillating"][i]),
                    "iae": finite(c["iae"][i]),
                },
                "counters": {
                    k: int(c[k][i]) for k in ("samples", "steps", "updates", "rejected", "quiet")
                },
            }
        )
    counts = np.bincount(c["status"], minlength=len(STATUS_NAMES)) if n else [0] * len(STATUSES)
    mode_counts = np.bincount(c["mode"], minlength=len(MODES)) if n else [0] * len(MODES)
    body = {
        "items": items,
        "total": n,
        "matched": int(rows.size),
        "offset": offset,
        "limit": limit,
        "statuses": {s: int(k) for s, k in zip(STATUS_NAMES, counts, strict=True)},
        "modes": {m.value: int(k) for m, k in zip(MODES, mode_counts, strict=True)},
        "trends": recent is not None,
        "server_ms": round((time.perf_counter() - started) * 1000, 1),
    }
    return JSONResponse(body, headers={"Cache-Control": "no-store"})


# -- the tuner --------------------------------------------------------------------------
@router.get("/api/tuner")
def tuner_data(request: Request) -> JSONResponse:
    tuner = tuner_of(request)
    figures = tuner_figures(tuner)
    with tuner.engine.lock:
        wall = time.time()
        statuses = tuner.table.status_counts(wall)
        modes = tuner.table.mode_counts()
    figures["loops"] = {
        "total": sum(modes.values()),
        "statuses": {s.value: n for s, n in statuses.items()},
        "modes": {m.value: n for m, n in modes.items()},
    }
    rates = app_state(request, "console_rates", Rates)
    figures["rates"] = rates.rates(
        time.monotonic(),
        {
            "received": figures["received"],
            "rejected": figures["rejected_total"],
            "updates": sum(figures["updates"].values()),
            "batches": figures["inference"]["batches"],
        },
    )
    return JSONResponse(json.loads(json.dumps(figures, default=str)))


# -- static assets ----------------------------------------------------------------------
@router.get("/static/{path:path}")
def static(path: str) -> Response:
    found = asset(path)
    if found is None:
        raise HTTPException(404, "no such asset")
    data, kind = found
    headers = {"Cache-Control": "public, max-age=3600", "X-Content-Type-Options": "nosniff"}
    return Response(data, media_type=kind, headers=headers)


# a loop's live data and the console's actions, under the same /ui prefix
router.include_router(stream.router)
router.include_router(actions.router)
