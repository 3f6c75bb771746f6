"""What every console route reads from the app: the tuner and its ring of recent
samples, the names of the table's status and mode codes, JSON-safe numbers."""

from __future__ import annotations

import math

from fastapi import HTTPException, Request

from service.engine.status import STATUSES
from service.wire.protocol import Mode

MODES = list(Mode)
"""A loop's mode by its code in the table."""
STATUS_NAMES = [s.value for s in STATUSES]
"""A loop's status name by its code in the table."""


def tuner_of(request: Request):
    """The app's tuner; 503 while it is starting."""
    tuner = getattr(request.app.state, "tuner", None)
    if tuner is None:
        raise HTTPException(503, "the tuner is starting")
    return tuner


def recent_of(tuner):
    """The tuner's ring of recent samples (:mod:`service.daemon.recent`), None without one."""
    return getattr(tuner, "recent", None)


def finite(x: float | None) -> float | None:
    """``x`` as a float, None for None, NaN or infinity (JSON has neither)."""
    return None if x is None or not math.isfinite(x) else float(x)
