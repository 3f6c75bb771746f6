"""The tuning engine: samples in, gain decisions out. No bus, no database, no HTTP.

Everything between a decoded sample and a gains decision lives here and in the modules
it uses: per-loop state (:mod:`service.engine.table`), the sample rules, decimation to
the RL period, integration, adoption of an operator's gains, the excitation gate, the
batched agent step and the safety guard. The daemon is this engine behind Zenoh, SQLite
and FastAPI; ``pitune evaluate``, the tests, and anyone with their own plant simulator
drive the same engine and get exactly what the daemon would publish::

    from service.engine import TuningEngine, LoopConfig
    eng = TuningEngine()                                 # the shipped agent
    eng.register(LoopConfig(id="L1", kp=0.5, ki=0.01, sample_period_s=1.0,
                            scaling={"k_hat": 1.2, "tau_hat": 30.0, "pv_scale": 10.0}))
    updates = eng.ingest([{"loop_id": "L1", "t": 0.0, "sp": 55.0, "pv": 53.2}])
    # -> [GainUpdate(loop_id, seq, t, kp, ki, dkp, dki, mode, reason), ...]

Samples are in engineering units (plant seconds), any number of loops per call, in
arrival order. A loop falls due when a sample's plant time reaches the end of its RL
period; due loops are stepped together in one agent call at the end of :meth:`ingest`
(or earlier, when a due loop receives another sample, so each step sees exactly the data
up to its own due sample). The result is deterministic for the same samples and wall
times (``wall`` drives the flood limit and staleness, unless the engine has a step-free
``clock``: :mod:`service.engine.steady`; and it is the audit rows' ``wall_time``).

All methods take the engine's :attr:`lock` themselves (re-entrant: a caller may hold it
across several calls, as the daemon does).
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable, Iterable
from itertools import repeat
from typing import Literal

import numpy as np

from service.agent.fast import Precision
from service.agent.model import Agent, load_agent
from service.engine import first_tuning, proposals, refusals, rules, stepping, verify, views, watch
from service.engine.audit import AuditRow
from service.engine.config import LoopConfig, LoopView
from service.engine.modes import PUBLISHING
from service.engine.plant_hold import PlantHold
from service.engine.refuted import remembered
from service.engine.saved import Saved
from service.engine.site import SiteDefaults
from service.engine.table import LoopTable
from service.engine.updates import GainUpdate, StepResult
from service.engine.views import RawView
from service.wire.decode import Columns, Decoded, Rejection, decode_values
from service.wire.flood import MAX_SAMPLE_RATE_HZ
from service.wire.protocol import LoopStatus, Mode, RejectReason

RejectHandler = Callable[[Rejection], None]


class TuningEngine:
    """Per-loop tuning state of any number of loops and one batched agent."""

    def __init__(
        self,
        agent: Agent | None = None,
        *,
        max_rate_hz: float = MAX_SAMPLE_RATE_HZ,
        inference_workers: int = 1,
        inference_precision: Precision | Literal["reference"] = "float32",
        on_reject: RejectHandler | None = None,
        verifying: bool = True,
        monitoring: bool = True,
        site: SiteDefaults | None = None,
        clock: Callable[[], float] | None = None,
    ) -> None:
        self.agent = agent if agent is not None else load_agent()
        self.table = LoopTable(
            self.agent,
            max_rate_hz=max_rate_hz,
            inference_workers=inference_workers,
            inference_precision=inference_precision,
            site=site,
        )
        self.lock = self.table.lock
        self.table.monitoring = monitoring
        self.table.clock = clock  # step-free: staleness and rates (service.engine.steady)
        self.on_reject = on_reject
        self.rejected: collections.Counter[RejectReason] = collections.Counter()
        """Samples rejected so far, by reason."""
        self.received = 0
        """Samples received so far (each ends accepted or in :attr:`rejected`)."""
        self.stepping = True
        """False: loops that fall due are not stepped (counted in :attr:`skipped`): the
        daemon's choice while its store cannot record a step."""
        self.skipped = 0
        self.table.verifying = verifying
        self._due: dict[int, None] = {}  # ordered set of slots
        self._stamp = np.zeros(0, np.int64)  # scratch of _distinct, one entry a slot

    # -- registration -----------------------------------------------------------------
    def register(self, config: LoopConfig, *, seq: int = 0, wall: float | None = None) -> None:
        """Add a new loop at its registered gains; ``seq`` continues an earlier loop's."""
        with self.lock:
            self.table.add(config, seq=seq, wall=_now(wall))

    def restore(
        self,
        config: LoopConfig,
        *,
        kp: float,
        ki: float,
        seq: int,
        hidden: bytes | None = None,
        runtime: str | None = None,
        saved: Saved | None = None,
        wall: float | None = None,
    ) -> None:
        """Add a loop as it was stored: its gains, seq and state snapshot (``hidden`` and
        ``runtime`` as stored, or ``saved``: parsed ahead, outside the lock)."""
        with self.lock:
            self.table.add(
                config, kp=kp, ki=ki, seq=seq, hidden=hidden, runtime=runtime, saved=saved,
                wall=_now(wall),
            )  # fmt: skip

    def add_many(
        self,
        configs: list[LoopConfig],
        *,
        kp: list[float] | None = None,
        ki: list[float] | None = None,
        seq: list[int] | None = None,
        saved: list[Saved | None] | None = None,
        wall: float | None = None,
    ) -> None:
        """Add loops at once, new (registered gains; ``seq``: continuing earlier loops')
        or as stored (``kp``, ``ki``, ``seq`` and their snapshots parsed, ``saved``): as
        :meth:`register` and :meth:`restore` one by one would (see :meth:`LoopTable.add_many
        <service.engine.table.LoopTable.add_many>`), in a fraction of the time."""
        with self.lock:
            self.table.add_many(configs, kp=kp, ki=ki, seq=seq, saved=saved, wall=_now(wall))

    def reconfigure(self, config: LoopConfig) -> None:
        with self.lock:
            self.table.reconfigure(config)

    def remove(self, loop_id: str) -> None:
        with self.lock:
            self._due.pop(self.table.slot(loop_id), None)
            self.table.remove(loop_id)

    def reset(self, loop_id: str, wall: float | None = None, actor: str = "") -> StepResult | None:
        """A fresh episode at the registered gains (see :meth:`LoopTable.reset`); ``actor``
        (who reset) goes into the audit row's detail."""
        with self.lock:
            self._due.pop(self.table.slot(loop_id), None)
            return self.table.reset(loop_id, _now(wall), actor=actor)

    def identify(self, loop_id: str, wall: float | None = None, actor: str = "") -> None:
        """Identify the loop again from scratch (``POST /loops/{id}/identify``): the
        identified scaling is dropped (a loop registered without a hint is 'identifying'
        again and not tuned until a new model is confident; a hinted loop goes back to its
        hint), the mismatch and envelope flags are cleared, the models refuted on the loop
        forgotten (:mod:`service.engine.refuted`); audit row 'identify' (with
        ``actor=<actor>`` when one is given, as a reset's). A change pending stays
        pending, judged under the scaling then in force (:func:`watch.restart
        <service.engine.watch.restart>`)."""
        with self.lock:
            s = self.table.slot(loop_id)
            self._due.pop(s, None)
            watch.restart(self.table, s, _now(wall), actor)

    def rollback(self, loop_id: str, wall: float | None = None, actor: str = "") -> StepResult:
        """Restore the last-good gains now (``POST /loops/{id}/rollback``): published in
        ``auto``, proposed in ``advisory``; ValueError when there is nothing to restore
        (the gains in force are the last-good ones) or the mode publishes nothing."""
        with self.lock:
            s = self.table.slot(loop_id)
            if not verify.changed(self.table, s):
                raise ValueError("the gains in force are the last-good gains")
            # refused before verify.fail, which records a verdict: a refusal changes nothing
            if self.table.mode[s] not in PUBLISHING:
                raise ValueError(f"a {self.table.mode_of(s).value} loop publishes no gains")
            self._due.pop(s, None)
            return verify.fail(self.table, s, "operator", _now(wall), figure=None, actor=actor)

    def accept(
        self, loop_id: str, seq: int, wall: float | None = None, actor: str = ""
    ) -> StepResult:
        """Accept an advisory loop's pending proposal ``seq`` (see :func:`proposals.accept`)."""
        with self.lock:
            s = self.table.slot(loop_id)
            self._due.pop(s, None)
            return proposals.accept(self.table, s, seq, _now(wall), actor)

    def reject(self, loop_id: str, seq: int, wall: float | None = None, actor: str = "") -> None:
        """Reject an advisory loop's pending proposal ``seq`` (see :func:`proposals.reject`)."""
        with self.lock:
            proposals.reject(self.table, self.table.slot(loop_id), seq, _now(wall), actor)

    def set_hold(self, hold: PlantHold) -> None:
        """Hold the plant, or release it (:data:`RELEASED <service.engine.plant_hold.
        RELEASED>`): while held the tuner changes no loop's gains of its own
        (:mod:`service.engine.plant_hold`). The loops due and not yet stepped are not
        stepped: their period ended as the hold began."""
        with self.lock:
            self.table.hold = hold
            if hold.held:
                self._due.clear()

    @property
    def hold(self) -> PlantHold:
        """The plant-wide hold in force (``held`` False: none)."""
        return self.table.hold

    def performance(self, loop_id: str):
        """The loop's figures, their history and its verification state."""
        with self.lock:
            return views.performance(self.table, self.table.slot(loop_id))

    def __contains__(self, loop_id: object) -> bool:
        return loop_id in self.table.slot_of

    def __len__(self) -> int:
        return len(self.table)

    def loop_ids(self) -> list[str]:
        with self.lock:
            return list(self.table.slot_of)

    # -- samples ----------------------------------------------------------------------
    def ingest(
        self, samples: list[dict] | Decoded, *, wall: float | None = None
    ) -> list[GainUpdate]:
        """Take samples (dicts as on the wire, each with its ``loop_id``; numpy floats are
        fine; or already decoded) and return the gain updates due after them, in decision
        order."""
        decoded = samples if isinstance(samples, Decoded) else decode_values(list(samples))
        with self.lock:
            results = self.ingest_decoded(decoded, wall=wall)
            last = self.flush(wall)
        if last is not None:
            results.append(last)
        return [u for r in results for u in r.updates()]

    def ingest_decoded(self, decoded: Decoded, *, wall: float | None = None) -> list[StepResult]:
        """:meth:`ingest` without the final :meth:`flush` (the daemon decides when to step
        loops that are due); returns the steps taken on the way (a due loop receiving
        another sample is stepped first)."""
        wall = _now(wall)
        results: list[StepResult] = []
        with self.lock:
            self.received += decoded.received
            for rejection in decoded.rejected:
                self._reject(rejection, wall)
            rows = decoded.rows
            if not len(rows):
                return results
            slot_of = self.table.slot_of
            n = len(rows)
            slots = decoded.slots
            if slots is None:
                slots = np.fromiter(map(slot_of.get, rows.loop_ids, repeat(-1, n)), np.int64, n)
            unknown = slots < 0
            if unknown.any():
                for i in np.flatnonzero(unknown).tolist():
                    self._reject(
                        Rejection(
                            int(rows.index[i]),
                            rows.loop_ids[i],
                            RejectReason.unknown_loop,
                            "not registered",
                        ),
                        wall,
                    )
                rows, slots = rows.take(~unknown), slots[~unknown]
            for run in self._segments(rows, slots):
                if run is None:
                    result = self.flush(wall)
                    if result is not None:
                        results.append(result)
                    continue
                part, part_slots = run
                due, rejections = rules.ingest(self.table, part_slots, part, wall)
                for i, reason, detail in rejections:
                    rejection = Rejection(int(part.index[i]), part.loop_ids[i], reason, detail)
                    self._reject(rejection, wall)
                for s in part_slots[due].tolist():
                    self._due[s] = None
                if self.table.decided:  # first tunings from models put in force
                    results.extend(self.table.decided)
                    self.table.decided.clear()
                results.extend(self._judge(wall))
        return results

    def _segments(self, rows: Columns, slots: np.ndarray):
        """Runs of rows of distinct loops, none due, in arrival order; ``None`` between two
        runs when the due loops must be stepped first (a due loop has another sample).

        Lazy: each run is ingested before the next is cut, so "due" is up to date.
        """
        pending = self._due
        due_now = np.fromiter(pending, np.int64, len(pending))
        if self._distinct(slots) and not np.isin(slots, due_now).any():
            yield rows, slots  # the usual case: one run
            return
        start, seen = 0, set()
        for i, s in enumerate(slots.tolist()):
            if s in seen or s in pending:
                if i > start:
                    yield rows.take(np.arange(start, i)), slots[start:i]
                start, seen = i, set()
                if s in pending:
                    yield None
            seen.add(s)
        yield rows.take(np.arange(start, slots.size)), slots[start:]

    def _distinct(self, slots: np.ndarray) -> bool:
        """No slot twice, in two scattered writes and reads (np.unique sorted each pass's
        thousands of rows: ~5 % of a busy member's worker). Of two equal slots at i and
        j, the scratch holds one of i, j: the other position reads back wrong."""
        if self._stamp.size < len(self.table.ids):
            self._stamp = np.zeros(len(self.table.ids), np.int64)
        order = np.arange(slots.size)
        self._stamp[slots] = order
        return bool((self._stamp[slots] == order).all())

    def flush(self, wall: float | None = None) -> StepResult | None:
        """Step every due loop in one batched agent call (None if none is due)."""
        with self.lock:
            if not self._due:
                return None
            slots = np.fromiter(self._due, np.int64, len(self._due))
            self._due.clear()
            if not self.stepping:
                self.skipped += slots.size
                return None
            started = time.perf_counter()
            result = stepping.step(self.table, slots, _now(wall))
            result.inference_s = time.perf_counter() - started
            return result

    def catch_up(self, wall: float | None = None) -> list[StepResult]:
        """Assess loops owed an assessment by the identification budget, one pass's worth
        (:mod:`service.engine.fit_budget`; the tuner calls it when no samples wait);
        returns the decisions their models made (first tunings, rescales)."""
        with self.lock:
            if not self.table.fits.owed and self.table.warm_run is None:
                return []
            watch.catch_up(self.table, _now(wall))
            first_tuning.flush(self.table)
            decided = list(self.table.decided)
            self.table.decided.clear()
            return decided

    @property
    def due(self) -> int:
        """Loops due for an RL step, waiting for :meth:`flush`."""
        return len(self._due)

    def _judge(self, wall: float) -> list[StepResult]:
        """Verdicts of the responses completed and oscillations started (verify.py)."""
        tb = self.table
        if not tb.to_judge:
            return []
        done = np.concatenate([d for d, _ in tb.to_judge])
        osc = np.concatenate([o for _, o in tb.to_judge])
        tb.to_judge.clear()
        if not tb.verifying:
            return []
        failed = verify.judge(tb, done, osc, wall)
        for result in failed:
            self._due.pop(tb.slot(result.loop_ids[0]), None)
        for s in tb.refuted:  # after the rollback: its gains stay, the model goes (kept
            # in mind: a model like it is not used again)
            watch.restart(tb, s, wall, why=watch.REFUTED, keep=remembered(tb, s))
        tb.refuted.clear()
        return failed

    def _reject(self, rejection: Rejection, wall: float) -> None:
        self.rejected[rejection.reason] += rejection.count
        # wrong_gateway names a loop of ANOTHER gateway: booked on it, any gateway could
        # fill that loop's counters and refused view and hide its own gateway's problems
        foreign = rejection.reason is RejectReason.wrong_gateway
        slot = None if foreign else self.table.slot_of.get(rejection.loop_id)
        if slot is not None:
            refusals.book(self.table, slot, rejection, wall)
        if self.on_reject is not None:
            self.on_reject(rejection)

    # -- views and persistence ----------------------------------------------------------
    def view(self, loop_id: str, wall: float | None = None) -> LoopView:
        with self.lock:
            return self.table.view(loop_id, _now(wall))

    def raw_views(self, offset: int, limit: int, wall: float | None = None) -> list[RawView]:
        """A page of loops in registration order, unparsed (parse outside the lock)."""
        wall = _now(wall)
        with self.lock:
            ids = list(self.table.slot_of)[offset : offset + limit]
            return [self.table.raw_view(loop_id, wall) for loop_id in ids]

    def status_counts(self, wall: float | None = None) -> dict[LoopStatus, int]:
        with self.lock:
            return self.table.status_counts(_now(wall))

    def mode_counts(self) -> dict[Mode, int]:
        with self.lock:
            return self.table.mode_counts()

    def drain_changes(self) -> tuple[list[tuple[float, float, int, str]], list[AuditRow]]:
        """Gains rows and audit rows to persist since the last call."""
        with self.lock:
            return self.table.drain_changes()

    def requeue(self, gains: list, audit: list[AuditRow]) -> None:
        with self.lock:
            self.table.requeue(gains, audit)

    def snapshot(self, loop_ids: Iterable[str] | None = None) -> list[tuple[str, bytes, str]]:
        with self.lock:
            return self.table.snapshot(loop_ids)


def _now(wall: float | None) -> float:
    return time.time() if wall is None else wall
