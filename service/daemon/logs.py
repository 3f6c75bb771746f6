"""The tuner's logging: one line format for pitune's and uvicorn's loggers, and the
rate-limited INFO lines an operator reads (registrations, gain changes, adoptions,
status changes).

:func:`configure` installs one handler on the root logger, text (``timestamp level
logger: message``) or JSON lines (``{"ts", "level", "logger", "message"}``, plus
``exc`` with a traceback); uvicorn runs with ``log_config=None`` so its loggers
propagate to that handler instead of printing their own format.

:class:`EventLog` turns gains messages published and the other audit rows into one INFO
line each, at most ``burst`` lines per kind (registered, agent, adopted, ...) and
``interval_s``; the rest are counted and summed up in one line once the interval is
over, so a 10,000-loop site stepping every RL period writes a few lines per interval,
not 10,000. :class:`StatusWatch`
logs the loops whose status (tuning, quiet, stale, manual, ...) changed since the last
check, through the same limiter.
"""

from __future__ import annotations

import collections
import datetime as dt
import json
import logging
import sys
import threading
import time
from collections.abc import Iterable
from typing import TextIO

import numpy as np

from service.wire.protocol import UpdateReason

TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
UVICORN_LOGGERS = ("uvicorn", "uvicorn.error", "uvicorn.access", "uvicorn.asgi")
PROBE_PATHS = frozenset({"/healthz", "/readyz", "/metrics"})
"""What supervisors and Prometheus poll: their answered requests are DEBUG lines."""
log = logging.getLogger("pitune.events")
GAINS_REASONS = frozenset(r.value for r in UpdateReason)
"""Audit reasons of the decisions a gains message carries (:meth:`EventLog.published`)."""


def _timestamp(record: logging.LogRecord) -> str:
    """ISO 8601, UTC, milliseconds: sortable and unambiguous across time zones."""
    moment = dt.datetime.fromtimestamp(record.created, dt.UTC)
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


class TextFormatter(logging.Formatter):
    def __init__(self) -> None:
        super().__init__(TEXT_FORMAT)

    def formatTime(self, record: logging.LogRecord, datefmt: str | None = None) -> str:  # noqa: N802
        return _timestamp(record)


class JsonFormatter(logging.Formatter):
    """One JSON object per line; a traceback goes into ``exc``, never across lines."""

    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "ts": _timestamp(record),
            "level": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry, ensure_ascii=False, default=str)


def configure(level: str = "info", fmt: str = "text", stream: TextIO | None = None) -> None:
    """One handler on the root logger for every logger of the process, uvicorn's too."""
    handler = logging.StreamHandler(sys.stderr if stream is None else stream)
    handler.setFormatter(JsonFormatter() if fmt == "json" else TextFormatter())
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level.upper())
    for name in UVICORN_LOGGERS:  # uvicorn's own handlers (if any) would print twice
        logger = logging.getLogger(name)
        logger.handlers.clear()
        logger.propagate = True
    access = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, QuietProbes) for f in access.filters):
        access.addFilter(QuietProbes())


class QuietProbes(logging.Filter):
    """uvicorn's access line of a probe or scrape (:data:`PROBE_PATHS`) answered below
    400 is a DEBUG line, not INFO: a probe every 2 s would write 43,200 lines a day that
    say nothing. Any other request, and a probe that failed, stays at INFO."""

    def filter(self, record: logging.LogRecord) -> bool:
        args = record.args
        if not (isinstance(args, tuple) and len(args) == 5):  # not an access line
            return True
        _client, method, path, _version, status = args
        if method not in ("GET", "HEAD") or str(path).split("?", 1)[0] not in PROBE_PATHS:
            return True
        if not isinstance(status, int) or status >= 400:
            return True
        # uvicorn sets its access logger's level (--log-level): a DEBUG line is written
        # only at debug; the root handler takes what the logger passes on
        if not logging.getLogger(record.name).isEnabledFor(logging.DEBUG):
            return False
        record.levelno, record.levelname = logging.DEBUG, "DEBUG"
        return True


class Limiter:
    """At most ``burst`` lines per key and ``interval_s``; the rest counted and summed
    up in one line (at the next line of that key after the interval, or :meth:`flush`)."""

    def __init__(
        self,
        logger: logging.Logger,
        burst: int = 20,
        interval_s: float = 10.0,
        clock=time.monotonic,
    ) -> None:
        self.logger = logger
        self.burst = burst
        self.interval_s = interval_s
        self.clock = clock
        self._lock = threading.Lock()
        self._window: dict[str, tuple[float, int, int]] = {}
        """key -> (window start, lines logged, lines suppressed)."""

    def take(self, key: str, n: int = 1) -> int:
        """How many of ``n`` lines of ``key`` may be logged now; the rest are counted."""
        now = self.clock()
        with self._lock:
            start, logged, suppressed = self._window.get(key, (now, 0, 0))
            if now - start >= self.interval_s:
                self._summary(key, suppressed, now - start)
                start, logged, suppressed = now, 0, 0
            allowed = max(0, min(n, self.burst - logged))
            self._window[key] = (start, logged + allowed, suppressed + n - allowed)
        return allowed

    def log(self, level: int, key: str, message: str, *args: object) -> bool:
        if not self.take(key):
            return False
        self.logger.log(level, message, *args)
        return True

    def flush(self) -> None:
        """Sum up the windows that are over (call it now and then: a burst may be the
        last of its kind for a long time)."""
        now = self.clock()
        with self._lock:
            for key, (start, _logged, suppressed) in list(self._window.items()):
                if now - start >= self.interval_s:
                    self._summary(key, suppressed, now - start)
                    del self._window[key]

    def _summary(self, key: str, suppressed: int, seconds: float) -> None:
        if suppressed:
            self.logger.info("%d more %s events not logged in %.0f s", suppressed, key, seconds)


def _gains(kp: float | None, ki: float | None) -> str:
    return "none" if kp is None else f"kp={kp:.6g} ki={ki:.6g}"


class EventLog:
    """One INFO line per change of a loop, rate-limited per kind: a gains message from the
    message published (:meth:`published`), any other change from its audit row
    (:meth:`audit`)."""

    def __init__(self, logger: logging.Logger = log, burst: int = 20, interval_s: float = 10.0):
        self.limiter = Limiter(logger, burst, interval_s)

    def published(self, messages: Iterable[dict]) -> None:
        """Log gains messages handed to the publishers (GainsMessage dicts), but resets:
        the API logs those with their caller. A step held or a shadow loop's has an audit
        row and no message: it is not logged as an update."""
        self._log((m["reason"], m) for m in messages if m["reason"] != UpdateReason.reset)

    def audit(self, rows: Iterable[tuple]) -> None:
        """Log audit rows (:data:`service.engine.audit.AUDIT_COLUMNS` order) but those of
        gains decisions (agent, model, rollback, accepted, reset), which
        :meth:`published` logs when (and only if) their message goes out: adoptions,
        registrations, patches, deletions, verdicts, identification outcomes, ..."""
        self._log((row[5], row) for row in rows if row[5] not in GAINS_REASONS)

    def _log(self, items: Iterable[tuple[str, object]]) -> None:
        if not self.limiter.logger.isEnabledFor(logging.INFO):
            return
        by_kind: dict[str, list] = collections.defaultdict(list)
        for kind, item in items:  # the worker calls this per step: format only what is logged
            by_kind[kind].append(item)
        for kind, group in by_kind.items():
            for item in group[: self.limiter.take(str(kind), len(group))]:
                text = self._update(item) if isinstance(item, dict) else self._message(item)
                self.limiter.logger.info("%s", text)

    @staticmethod
    def _update(m: dict) -> str:
        old = _gains(m["kp"] - m["dkp"], m["ki"] - m["dki"])
        return (
            f"loop {m['loop_id']!r} gains {old} -> {_gains(m['kp'], m['ki'])} "
            f"({m['reason']}, {m['mode']}, seq {m['seq']}) at t={m['t']:g}"
        )

    @staticmethod
    def _message(row: tuple) -> str:
        loop_id, _wall, t, seq, mode, reason, kp0, ki0, kp1, ki1, detail = row
        at = "" if t is None else f" at t={t:g}"
        if reason == "registered":
            return f"loop {loop_id!r} registered ({mode}, {_gains(kp1, ki1)}, seq {seq})"
        if reason == "deleted":
            return f"loop {loop_id!r} deleted ({mode}, last {_gains(kp0, ki0)})"
        if reason == "patched":
            return f"loop {loop_id!r} config changed: {detail} (now {mode})"
        if reason == "adopted":
            return (
                f"loop {loop_id!r} adopted the gateway's gains {_gains(kp1, ki1)} "
                f"(were {_gains(kp0, ki0)}){at}: an operator's change"
            )
        # verdicts, identification outcomes, faults, ...: no gains published
        return f"loop {loop_id!r} {reason} ({mode}, {_gains(kp1, ki1)}, seq {seq}){at}: {detail}"

    def flush(self) -> None:
        self.limiter.flush()


class StatusWatch:
    """Logs the loops whose status changed since the previous :meth:`check`.

    It compares the table's status codes slot by slot (numpy), and builds a line only for
    the slots that changed: a dict of every loop's status, built under the table's lock
    and compared in Python, took 60 + 80 ms of a 150,000-loop member every check, and
    the worker waited for the lock and then for the interpreter (a tail in the update
    latency every 5 s, the check's period)."""

    def __init__(self, events: EventLog) -> None:
        self.events = events
        self._ids: list[str | None] = []
        self._codes = np.zeros(0, np.int8)

    def check(self, ids: list[str | None], codes: np.ndarray) -> list[tuple[str, str, str]]:
        """``ids``: the loop in each table slot (None: free), ``codes``: each slot's
        status, an index into :data:`~service.engine.status.STATUSES` (aligned). Logs and
        returns (id, old, new) for each change; a loop seen for the first time (a new or
        reused slot) is not a change (its registration is)."""
        from service.engine.status import STATUSES

        n = min(len(self._codes), codes.size)
        moved = np.flatnonzero(codes[:n] != self._codes[:n]).tolist()
        changes = [
            (ids[s], STATUSES[self._codes[s]].value, STATUSES[codes[s]].value)
            for s in moved
            if ids[s] is not None and ids[s] == self._ids[s]
        ]
        self._ids, self._codes = ids, codes.astype(np.int8)
        for loop_id, old, new in changes:
            self.events.limiter.log(
                logging.INFO, "status", "loop %r status %s -> %s", loop_id, old, new
            )
        return changes


def table_statuses(table, wall: float) -> tuple[list[str | None], np.ndarray]:
    """The loop in each slot of a :class:`~service.engine.table.LoopTable` and its status
    code, for :meth:`StatusWatch.check` (hold the table's lock): one vectorised pass
    over every slot, free ones included (their codes are ignored), and a copy of the
    slots' ids."""
    ids = list(table.ids)
    return ids, table.statuses(np.arange(len(ids)), wall)
