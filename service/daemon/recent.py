"""The recent samples and published gains of every loop, in memory, for the console's trends.

:class:`Recent` keeps, per registered loop, a ring of the last :data:`POINTS` accepted
samples (plant time, setpoint, error, controller output, the gains the gateway reports)
and a ring of the last :data:`GAINS` gains decisions the tuner published (wall time,
plant time, kp, ki, reason). Nothing here is persisted: after a restart the trends start
empty (the audit log in the store keeps every change).

Size, fixed per loop and allocated the first time a loop sends a sample (for every
registered loop at once, then a quarter more at a time; the samples' part in zeroed
pages the OS maps as they are first written):

* samples: ``t`` float64 + ``sp``, ``e``, ``op``, ``kp``, ``ki`` float32 = 28 bytes a point
  (one record, :data:`POINT`, padded to 32), x :data:`POINTS` (256) = 8 KB per loop;
* gains: ``wall``, ``t``, ``kp``, ``ki`` float64 + reason code = 33 bytes, x :data:`GAINS`
  (32) = 1 KB per loop, and the gains the last decision replaced (16 bytes);

so about 9 KB per loop: 90 MB at 10,000 loops (``Recent(points=..., gains=...)`` to
change it; ``nbytes`` says what is allocated). 256 points are 4 minutes of a loop
sampled every second: the trend shows recent behaviour, the audit log the long story.

Writes are vectorised (one numpy scatter of records per batch of decoded samples, however
many loops it holds). A point's fields sit together in one record, so a sample costs one
random memory access of the ring; a field per array cost six, most of the ring's time
at 30,000 loops and more. Writes come from the tuner's worker, reads from the API's
threads, serialised by the ring's own lock (held for microseconds, never the engine's).
Samples of ids that are not registered are ignored (``known``: the engine's id-to-slot
mapping, read under the engine lock the worker already holds).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Mapping
from itertools import repeat
from typing import Any

import numpy as np

from service.wire.protocol import UpdateReason

POINTS = 256
"""Samples kept per loop."""
GAINS = 32
"""Published gains decisions kept per loop."""
REASONS = [*map(str, UpdateReason), "other"]
"""Reason codes of the gains ring: the published reasons (an unknown one is 'other')."""
_SAMPLE_F32 = ("sp", "e", "op", "kp", "ki")
POINT = np.dtype(
    {
        "names": ["t", *_SAMPLE_F32],
        "formats": [np.float64] + [np.float32] * len(_SAMPLE_F32),
        "offsets": [0, 8, 12, 16, 20, 24],
        "itemsize": 32,
    }
)
"""One sample of the ring: its fields together, 28 bytes padded to 32, so that a batch's
points go into the ring as rows of 4 uint64 (numpy copies a plain row per index; a
scatter or fill of structured records takes its slow path, field by field: 4x slower)."""
log = logging.getLogger("pitune.tuner")


class Recent:
    """Bounded per-loop rings of recent samples and published gains (see the module doc)."""

    def __init__(
        self,
        known: Mapping[str, Any] | None = None,
        points: int = POINTS,
        gains: int = GAINS,
        capacity: int = 64,
        table: Any = None,
    ) -> None:
        self.table = table
        """The engine's table, whose slots (the gateway check's) index :attr:`_by_table`."""
        self.known = table.slot_of if known is None and table is not None else known
        self._by_table = np.empty(0, np.int64)
        """Ring slot of each table slot (-1: not yet looked up), valid while the table's
        ``version`` is :attr:`_by_version` (no loop added or removed)."""
        self._by_version = -1
        self._seen = -1
        """The table's version at the last batch (the map is rebuilt once it holds)."""
        self.points = int(points)
        self.gains_n = int(gains)
        self.lock = threading.Lock()
        self._failed_at = -math.inf
        self.slot_of: dict[str, int] = {}
        self._free: list[int] = []
        self._cap = 0
        self._grow(capacity)

    # -- storage ----------------------------------------------------------------------
    def _grow(self, capacity: int) -> None:
        old = self._cap
        p, g = self.points, self.gains_n

        def grown(arr: np.ndarray | None, shape: tuple, dtype, fill) -> np.ndarray:
            new = np.full(shape, fill, dtype)
            if arr is not None and old:
                new[:old] = arr
            return new

        # zeros: pages the OS maps when first written, no fill (a ring of 150,000 loops is
        # 1.2 GB, and filling it stalled the worker for seconds); ``n`` says which points
        # of a slot hold samples
        bits = np.zeros((p, capacity, 4), np.uint64)
        if old:
            bits[:, :old] = self._bits
        self._bits = bits
        """The ring's memory, a point as 4 uint64 (what writes copy), point-major: the
        loops of one gateway batch have neighbouring slots (allocated as they first came)
        and the same point index (as many samples each), so a batch writes one contiguous
        run where slot-major rows took a page (and a TLB miss) per sample: the ring's
        write was a fifth of a cluster member's CPU at 150,000 loops."""
        self.ring = bits.view(POINT).reshape(p, capacity).T
        """(slots, points) records (a view); a loop's next sample goes to ``n % points``."""
        self.n = grown(getattr(self, "n", None), (capacity,), np.int64, 0)
        """Samples ever written per slot (the next one goes to ``n % points``)."""
        self.g_wall = grown(getattr(self, "g_wall", None), (capacity, g), np.float64, np.nan)
        self.g_t = grown(getattr(self, "g_t", None), (capacity, g), np.float64, np.nan)
        self.g_kp = grown(getattr(self, "g_kp", None), (capacity, g), np.float64, np.nan)
        self.g_ki = grown(getattr(self, "g_ki", None), (capacity, g), np.float64, np.nan)
        self.g_reason = grown(getattr(self, "g_reason", None), (capacity, g), np.uint8, 0)
        self.g_n = grown(getattr(self, "g_n", None), (capacity,), np.int64, 0)
        self.g_from = grown(getattr(self, "g_from", None), (capacity, 2), np.float64, np.nan)
        """The gains in force the last decision changed (a proposal: would change), kp
        and ki: what its change is measured against (:meth:`summary`)."""
        self._free.extend(range(capacity - 1, old - 1, -1))
        self._cap = capacity

    def _room(self) -> int:
        """The capacity to grow to: every registered loop at once (each allocation copies
        the ring: at 75,000 loops doubling allocated and copied 1.5 GB, and kept 56,000
        slots spare), and a quarter more than now at least."""
        return max(len(self.known or ()), self._cap + self._cap // 4 + 64)

    @property
    def nbytes(self) -> int:
        """Bytes held by the rings."""
        names = ("ring", "n", "g_wall", "g_t", "g_kp", "g_ki", "g_reason", "g_n", "g_from")
        return sum(getattr(self, name).nbytes for name in names)

    def _slots(self, ids: list[str]) -> np.ndarray:
        """Ring slots of ``ids`` (-1: not a registered loop), allocating new ones."""
        slots = list(map(self.slot_of.get, ids, repeat(-1, len(ids))))
        if -1 in slots:
            for k, loop_id in enumerate(ids):
                if slots[k] != -1:
                    continue
                if loop_id in self.slot_of:
                    slots[k] = self.slot_of[loop_id]
                elif self.known is None or loop_id in self.known:
                    if not self._free:
                        self._grow(self._room())
                    s = self._free.pop()
                    self.slot_of[loop_id] = s
                    slots[k] = s
        return np.asarray(slots, np.int64)

    def _slots_of(self, ids: list[str], table_slots: np.ndarray | None) -> np.ndarray:
        """Ring slots of ``ids``, through their table slots where given: an id looked up
        in a dict of every loop is a cache miss or two per sample (6-7 % of a cluster
        member's CPU at 150,000 loops), an index into :attr:`_by_table` one read."""
        tb = self.table
        if table_slots is None or tb is None:
            return self._slots(ids)
        if self._by_version != tb.version or len(self._by_table) < len(tb.ids):
            if self._seen != tb.version:  # loops coming or going (a takeover's chunks):
                self._seen = tb.version  # look up by id until they stop, not a new
                return self._slots(ids)  # map of every slot at each batch
            self._by_table = np.full(len(tb.ids), -1, np.int64)
            self._by_version = tb.version
        known = table_slots >= 0
        ring = np.where(known, self._by_table[np.where(known, table_slots, 0)], -1)
        miss = np.flatnonzero(known & (ring < 0))
        if miss.size:
            found = self._slots([ids[i] for i in miss.tolist()])
            ring[miss] = found
            self._by_table[table_slots[miss]] = found
        return ring

    def _clear(self, s: int) -> None:
        self.n[s] = 0  # its points are unwritten again
        self.g_wall[s] = self.g_t[s] = self.g_kp[s] = self.g_ki[s] = self.g_from[s] = np.nan
        self.g_n[s] = 0

    def forget(self, loop_id: str) -> None:
        """Drop a loop's rings (deleted)."""
        with self.lock:
            s = self.slot_of.pop(loop_id, None)
            if s is not None:
                self._clear(s)
                self._free.append(s)
                self._by_version = -1  # its ring slot may serve another loop next

    def retain(self, loop_ids: Mapping[str, Any] | set[str]) -> int:
        """Drop the rings of loops not in ``loop_ids`` (deleted meanwhile); how many."""
        with self.lock:
            gone = [i for i in self.slot_of if i not in loop_ids]
        for loop_id in gone:
            self.forget(loop_id)
        return len(gone)

    # -- writes (the tuner's worker) ---------------------------------------------------
    def add_samples(self, columns: Any) -> None:
        """Accepted or not yet judged samples as decoded columns
        (:class:`service.wire.decode.Columns`: ``loop_ids``, ``t``, ``sp``, ``e``, ``kp``,
        ``ki``, optional ``op``) or what holds them (``Decoded.rows``), in order; rows of
        unknown loops are skipped; a ``Decoded`` with the table slots of its rows
        (``slots``) saves the id lookups."""
        table_slots = getattr(columns, "slots", None)
        columns = getattr(columns, "rows", columns)
        ids = columns.loop_ids
        if not len(ids):
            return
        with self.lock:
            slots = self._slots_of(ids, table_slots)
            keep = np.flatnonzero(slots >= 0)
            if not keep.size:
                return
            slots = slots[keep]
            order = np.argsort(slots, kind="stable")
            ordered = slots[order]
            starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
            counts = np.diff(np.r_[starts, ordered.size])
            rank = np.arange(ordered.size) - np.repeat(starts, counts)
            total = np.repeat(counts, counts)
            last = rank >= total - self.points  # only the newest `points` of a loop
            rows = keep[order][last]
            s = ordered[last]
            pos = (self.n[s] + rank[last]) % self.points
            points = np.empty(rows.size, POINT)
            points["t"] = np.asarray(columns.t)[rows]
            for name in _SAMPLE_F32:
                values = getattr(columns, name, None)
                points[name] = np.nan if values is None else np.asarray(values)[rows]
            self._bits[pos, s] = points.view(np.uint64).reshape(-1, 4)
            self.n[ordered[starts]] += counts

    def add_gains(self, result: Any, wall: float | None = None) -> None:
        """A published decision (:class:`service.engine.updates.StepResult`:
        ``loop_ids``, ``t``, ``old`` and ``new`` (n, 2), ``reason``)."""
        ids = result.loop_ids
        if not len(ids):
            return
        wall = time.time() if wall is None else wall
        reason = getattr(result.reason, "value", result.reason)
        code = REASONS.index(reason) if reason in REASONS else len(REASONS) - 1
        new = np.asarray(result.new, np.float64).reshape(-1, 2)
        old = np.asarray(result.old, np.float64).reshape(-1, 2)
        t = np.asarray(result.t, np.float64)
        with self.lock:
            slots = self._slots(list(ids))
            for k in np.flatnonzero(slots >= 0).tolist():  # one decision per loop and step
                s = int(slots[k])
                pos = self.g_n[s] % self.gains_n
                self.g_wall[s, pos] = wall
                self.g_t[s, pos] = t[k]
                self.g_kp[s, pos], self.g_ki[s, pos] = new[k]
                self.g_reason[s, pos] = code
                self.g_from[s] = old[k]
                self.g_n[s] += 1

    def safely(self, add, data) -> None:
        """``add(data)``, logging (once a minute) instead of raising: the trends must
        never stop the tuner's worker."""
        try:
            add(data)
        except Exception:
            now = time.monotonic()
            if now - self._failed_at > 60.0:
                self._failed_at = now
                log.exception("recording recent samples failed (the trends miss them)")

    # -- reads (the console) -----------------------------------------------------------
    def count(self, loop_id: str) -> tuple[int, int]:
        """(samples, gains decisions) ever written for the loop."""
        with self.lock:
            s = self.slot_of.get(loop_id)
            return (0, 0) if s is None else (int(self.n[s]), int(self.g_n[s]))

    def since(self, loop_id: str, samples_seen: int = 0, gains_seen: int = 0) -> dict:
        """The loop's points after the first ``samples_seen`` samples and
        ``gains_seen`` decisions (what the ring still holds of them), JSON-ready: columns
        with None for NaN, ``n``/``gn``: the counts to pass next time."""
        with self.lock:
            s = self.slot_of.get(loop_id)
            if s is None:
                return {"n": 0, "gn": 0, "t": [], "sp": [], "pv": [], "op": [], "kp": [],
                        "ki": [], "gains": []}  # fmt: skip
            n, gn = int(self.n[s]), int(self.g_n[s])
            # a count beyond the loop's (a client's stale or made-up cursor) asks for nothing
            first = min(max(samples_seen, n - self.points, 0), n)
            idx = np.arange(first, n) % self.points
            points = self.ring[s, idx]
            t = points["t"].copy()
            sp, e, op, kp, ki = (points[name].astype(np.float64) for name in _SAMPLE_F32)
            gfirst = min(max(gains_seen, gn - self.gains_n, 0), gn)
            gidx = np.arange(gfirst, gn) % self.gains_n
            gains = [
                {"wall": w, "t": _num(tt), "kp": p, "ki": i, "reason": REASONS[r]}
                for w, tt, p, i, r in zip(
                    self.g_wall[s, gidx].tolist(), self.g_t[s, gidx].tolist(),
                    self.g_kp[s, gidx].tolist(), self.g_ki[s, gidx].tolist(),
                    self.g_reason[s, gidx].tolist(), strict=True,
                )
            ]  # fmt: skip
        pv = sp - e
        return {
            "n": n,
            "gn": gn,
            "t": _col(t),
            "sp": _col(sp),
            "pv": _col(pv),
            "e": _col(e),
            "op": _col(op),
            "kp": _col(kp),
            "ki": _col(ki),
            "gains": gains,
        }

    def summary(self, loop_ids: list[str]) -> dict[str, np.ndarray]:
        """Per loop of ``loop_ids``, vectorised: ``last_wall`` of the last published gains
        (NaN: none since start), its ``reason`` code, ``dkp``/``dki`` (relative change of
        that decision against the gains in force it changed, or a proposal would change:
        what an accepted proposal changed on the plant, where the proposal published
        before it showed 0; NaN if unknown), ``rms_e`` (rms error over the ring, NaN
        without samples)."""
        m = len(loop_ids)
        out = {k: np.full(m, np.nan) for k in ("last_wall", "dkp", "dki", "rms_e")}
        out["reason"] = np.full(m, -1, np.int64)
        with self.lock:
            slots = np.fromiter((self.slot_of.get(i, -1) for i in loop_ids), np.int64, m)
            has = np.flatnonzero(slots >= 0)
            if not has.size:
                return out
            s = slots[has]
            gn = self.g_n[s]
            got = gn > 0
            last = (gn - 1) % self.gains_n
            rows, k = has[got], s[got]
            out["last_wall"][rows] = self.g_wall[k, last[got]]
            out["reason"][rows] = self.g_reason[k, last[got]]
            with np.errstate(divide="ignore", invalid="ignore"):
                out["dkp"][rows] = self.g_kp[k, last[got]] / self.g_from[k, 0] - 1.0
                out["dki"][rows] = self.g_ki[k, last[got]] / self.g_from[k, 1] - 1.0
            e = self.ring["e"][s]
            e = np.where(np.arange(self.points) < self.n[s][:, None], e, np.nan)  # written
            with np.errstate(invalid="ignore"), _quiet():
                out["rms_e"][has] = np.sqrt(np.nanmean(np.square(e, dtype=np.float64), axis=1))
        return out


class _quiet:
    """Silence numpy's 'mean of empty slice' warning (a loop without samples: NaN)."""

    def __enter__(self):
        import warnings

        self._w = warnings.catch_warnings()
        self._w.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc):
        self._w.__exit__(*exc)


def _num(x: float) -> float | None:
    return None if math.isnan(x) else x


def _col(values: np.ndarray) -> list[float | None]:
    return [None if v != v else v for v in values.tolist()]


def attach(tuner: Any, points: int = POINTS, gains: int = GAINS) -> Recent:
    """Give a :class:`~service.daemon.tuner.Tuner` a ring fed by its worker, unless it has
    one (the daemon's own wiring): wraps the engine's ``ingest_decoded`` and the tuner's
    ``_publish``. For tests and tools that run a tuner without that wiring."""
    existing = getattr(tuner, "recent", None)
    if isinstance(existing, Recent):
        return existing
    recent = Recent(points=points, gains=gains, table=tuner.table)
    engine = tuner.engine
    ingest = engine.ingest_decoded
    publish = tuner._publish

    def ingest_decoded(decoded, *args, **kwargs):
        recent.safely(recent.add_samples, decoded)
        return ingest(decoded, *args, **kwargs)

    def _publish(result):
        recent.safely(recent.add_gains, result)
        return publish(result)

    engine.ingest_decoded = ingest_decoded
    tuner._publish = _publish
    tuner.recent = recent
    return recent
