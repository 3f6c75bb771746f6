"""Per-loop runtime state, kept in numpy arrays indexed by a loop's slot.

For each accepted sample the table integrates the error (trapezoid on the plant's
timestamps), decimates to the RL period by sample time (never wall time, so an
accelerated simulation tunes as fast as it publishes) and says whether the loop is
due for an RL step. :meth:`LoopTable.step` then steps every due loop in one batched
agent call and applies the safety guard, vectorised over the batch.

Safety guard, per loop:

* new gains are clipped to the loop's absolute bounds, then to at most a relative
  change ``r`` per update ([old / (1 + r), old * (1 + r)], symmetric in log space), so
  a gain outside its bounds (an operator's choice) is walked back gradually;
* no RL step while the gateway reports manual mode or a saturated output, and none
  across a gap of more than ``stale_periods`` sample periods (the decimation window
  restarts at the first sample after the gap, and the integral does not bridge it).
  Nor is the error integrated while in manual or saturated (training never saw an
  integral wound up by an error nobody controls), and the decimation window restarts
  at the first sample back in auto, so a step sees a full RL period of control;
* ``frozen`` loops are never stepped; ``advisory`` loops are stepped and their
  proposals published, but their gains change only when the gateway reports them;
* excitation gate: the agent learns from setpoint responses, and stepped on a loop
  whose setpoint stands still it walks the gains far from where they were (see the
  evaluation's quiet-loop line). A loop is stepped only in RL periods that end within
  ``excitation_periods`` RL periods of a setpoint change of at least
  ``excitation_min_step`` (agent units; for gateways that send only the error, a jump
  of the error between two samples). Other periods leave the gains and the hidden
  state untouched and count as ``quiet``.

Gains the gateway reports in a sample are adopted when they differ from the tuner's
(an operator changed them), except when they are exactly the gains an auto update just
replaced: then the update is still in flight and adopting would undo it.

Every method must be called with :attr:`LoopTable.lock` held; the table is shared by
the bus worker and the admin API. Changes to persist (new gains, audit rows) accumulate
until :meth:`LoopTable.drain_changes`.
"""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import orjson

from service.agent.fast import FastPolicy, Precision
from service.agent.model import Agent
from service.engine.audit import AuditRow, audit_row
from service.engine.config import Counters, LoopConfig, LoopView
from service.engine.updates import MODE_VALUES, StepResult
from service.wire.decode import Columns
from service.wire.protocol import LoopStatus, Mode, RejectReason, UpdateReason

MAX_AGENT_ERROR = 100.0
"""An error beyond this many agent units (training sees about 2) is an absurd sample."""
CLOCK_RESET_SAMPLES = 10
"""Consecutive, mutually increasing samples older than the loop's last one that are
taken as a new plant clock (a restarted gateway, or a last sample from the far future)
rather than rejected forever as out of order."""
GAIN_RTOL = 1e-6
"""Relative tolerance when comparing reported gains with the tuner's: a DCS storing gains
as float32 reports them off by up to 6e-8 relative, which is no operator's change."""

_MODES = list(Mode)
_CODE = {m: i for i, m in enumerate(_MODES)}
AUTO, ADVISORY, FROZEN = (_CODE[m] for m in (Mode.auto, Mode.advisory, Mode.frozen))
STATUSES = [
    LoopStatus.frozen, LoopStatus.waiting, LoopStatus.stale, LoopStatus.manual,
    LoopStatus.saturated, LoopStatus.quiet, LoopStatus.tuning,
]  # fmt: skip
"""Statuses in order of precedence (see :meth:`LoopTable.statuses`)."""

_F64 = (
    # gains now, registered, and replaced by an update still in flight
    "kp", "ki", "reg_kp", "reg_ki", "prev_kp", "prev_ki",
    # unit mapping (engineering per agent) and timing
    "kp_unit", "ki_unit", "e_scale", "int_scale", "period", "stale_gap", "forgetting",
    # episode state
    "last_t", "last_e", "int_e", "next_due", "last_wall",
    # safety guard and flood limiter
    "kp_min", "kp_max", "ki_min", "ki_max", "max_rel", "tokens", "token_wall",
    # excitation gate: smallest setpoint step (engineering units), window after one (s;
    # inf: gate off), setpoint at the last step, end of the current window
    "exc_step", "exc_window", "sp_ref", "excited_until",
    # run of out-of-order samples that may be a new clock: length and last t
    "back_n", "back_t",
)  # fmt: skip
_I64 = ["mode", "seq", "n_samples", "n_rejected", "n_steps", "n_updates", "n_quiet"]
_BOOL = ["pending", "manual", "saturated"]


class Configs:
    """Loop configs by id, held as compact JSON (a parsed :class:`LoopConfig` costs ~2.4 KB
    per loop; its JSON ~0.3 KB). Reading one parses it: only the admin API does."""

    def __init__(self) -> None:
        self._json: dict[str, bytes] = {}

    def __getitem__(self, loop_id: str) -> LoopConfig:
        return LoopConfig.model_validate_json(self._json[loop_id])

    def raw(self, loop_id: str) -> bytes:
        """The config's JSON, unparsed (to parse it outside the table's lock)."""
        return self._json[loop_id]

    def __setitem__(self, loop_id: str, config: LoopConfig) -> None:
        self._json[loop_id] = config.model_dump_json().encode()

    def __delitem__(self, loop_id: str) -> None:
        del self._json[loop_id]

    def __contains__(self, loop_id: object) -> bool:
        return loop_id in self._json

    def __len__(self) -> int:
        return len(self._json)


@dataclass
class RawView:
    """A loop's view with its config still JSON: see :meth:`LoopTable.raw_view`."""

    config: bytes
    kp: float
    ki: float
    status: LoopStatus
    seq: int
    last_sample_t: float | None
    int_e: float
    hidden_norm: float
    counters: Counters

    def parse(self) -> LoopView:
        config = LoopConfig.model_validate_json(self.config)
        scaling = config.resolved_scaling
        return LoopView(
            config=config,
            scaling=scaling,
            rl_period_s=scaling.rl_period_s,
            mode=config.mode,
            kp=self.kp,
            ki=self.ki,
            status=self.status,
            seq=self.seq,
            last_sample_t=self.last_sample_t,
            int_e=self.int_e,
            hidden_norm=self.hidden_norm,
            counters=self.counters,
        )


class LoopTable:
    """Runtime state of all registered loops; one batched agent per table."""

    def __init__(
        self,
        agent: Agent,
        *,
        max_rate_hz: float,
        capacity: int = 64,
        inference_workers: int = 1,
        inference_precision: Precision = "float32",
    ) -> None:
        self.agent = agent
        # the allocation-free equivalent of agent.act (any other object: its own act)
        self._policy = (
            FastPolicy(agent, workers=inference_workers, precision=inference_precision)
            if isinstance(agent, Agent)
            else None
        )
        self.inference_precision = self._policy.precision if self._policy else "agent.act"
        self.lock = threading.RLock()
        self.rate = float(max_rate_hz)
        self.burst = max(self.rate, 1.0)
        self.configs = Configs()
        self.slot_of: dict[str, int] = {}
        self.ids: list[str | None] = []
        self.gateways: list[str | None] = []
        self._free: list[int] = []
        self._gains_dirty: set[int] = set()
        self._audit: list[AuditRow] = []
        self._allocate(capacity)

    # -- storage ----------------------------------------------------------------------
    def _allocate(self, capacity: int) -> None:
        old = len(self.ids)
        layers, hidden = self.agent.cfg.layers, self.agent.cfg.hidden
        for names, dtype in ((_F64, np.float64), (_I64, np.int64), (_BOOL, bool)):
            for name in names:
                arr = np.zeros(capacity, dtype)
                if old:
                    arr[:old] = getattr(self, name)
                setattr(self, name, arr)
        h = np.zeros((capacity, layers, hidden), np.float32)
        if old:
            h[:old] = self.hidden
        self.hidden = h
        self.ids.extend([None] * (capacity - old))
        self.gateways.extend([None] * (capacity - old))
        self._free.extend(range(capacity - 1, old - 1, -1))

    def __len__(self) -> int:
        return len(self.slot_of)

    def mode_of(self, s: int) -> Mode:
        return _MODES[self.mode[s]]

    def slot(self, loop_id: str) -> int:
        """Slot of a registered loop; KeyError if unknown."""
        return self.slot_of[loop_id]

    # -- registration -----------------------------------------------------------------
    def add(
        self,
        config: LoopConfig,
        *,
        kp: float | None = None,
        ki: float | None = None,
        seq: int = 0,
        hidden: bytes | None = None,
        runtime: str | None = None,
        wall: float,
    ) -> int:
        """Register a loop (new: registered gains; restored: stored gains and snapshot)."""
        if config.id in self.slot_of:
            raise KeyError(f"loop {config.id!r} already registered")
        if not self._free:
            self._allocate(2 * len(self.ids))
        s = self._free.pop()
        self.ids[s] = config.id
        self.slot_of[config.id] = s
        self.reg_kp[s], self.reg_ki[s] = config.kp, config.ki
        self.kp[s] = config.kp if kp is None else kp
        self.ki[s] = config.ki if ki is None else ki
        self.seq[s] = seq
        for name in _I64[2:]:
            getattr(self, name)[s] = 0
        self.tokens[s], self.token_wall[s] = self.burst, wall
        self._configure(s, config)
        self._restart(s)
        if hidden is not None and runtime is not None:
            self._restore(s, hidden, runtime)
        return s

    def _configure(self, s: int, config: LoopConfig) -> None:
        self.configs[config.id] = config
        sc = config.resolved_scaling
        g = config.guard
        self.kp_unit[s], self.ki_unit[s] = sc.kp_per_agent, sc.ki_per_agent
        self.e_scale[s] = sc.e_scale
        self.int_scale[s] = sc.int_scale
        self.period[s] = sc.rl_period_s
        self.stale_gap[s] = g.stale_periods * config.sample_period_s
        self.forgetting[s] = config.forgetting
        self.kp_min[s], self.kp_max[s] = g.kp_min, g.kp_max
        self.ki_min[s], self.ki_max[s] = g.ki_min, g.ki_max
        self.max_rel[s] = g.max_rel_change
        self.exc_step[s] = g.excitation_min_step / sc.e_scale
        self.exc_window[s] = g.excitation_periods * sc.rl_period_s or math.inf
        self.mode[s] = _CODE[config.mode]
        self.gateways[s] = config.gateway

    def _restart(self, s: int) -> None:
        """A fresh episode: zero hidden state and integral, no time reference."""
        self.hidden[s] = 0.0
        self.int_e[s] = self.last_e[s] = 0.0
        self.last_t[s] = self.next_due[s] = self.sp_ref[s] = math.nan
        self.excited_until[s] = -math.inf
        self.back_n[s] = 0.0
        self.last_wall[s] = -math.inf
        self.pending[s] = self.manual[s] = self.saturated[s] = False

    def reconfigure(self, config: LoopConfig) -> None:
        self._configure(self.slot(config.id), config)

    def remove(self, loop_id: str) -> None:
        s = self.slot_of.pop(loop_id)
        del self.configs[loop_id]
        self.ids[s] = None
        self._gains_dirty.discard(s)
        self._free.append(s)

    def reset(self, loop_id: str, wall: float) -> StepResult | None:
        """A fresh episode and the registered gains; the result is to be published.

        The gains move as an agent step's would: an ``auto`` loop takes them at once, as
        an update in flight (the gateway's next samples still report the old gains, which
        must not be adopted back); an ``advisory`` loop keeps its gains until the gateway
        reports new ones. A ``frozen`` loop gets no gains messages, so only its episode
        restarts and its gains stay those in force: None, nothing to publish.
        """
        s = self.slot(loop_id)
        old = (float(self.kp[s]), float(self.ki[s]))
        new = (float(self.reg_kp[s]), float(self.reg_ki[s]))
        t = self.last_t[s]
        t = None if math.isnan(t) else float(t)
        self._restart(s)
        mode = self.mode[s]
        if mode == FROZEN:
            self._audit.append(
                audit_row(loop_id, wall, t, int(self.seq[s]), Mode.frozen.value, "reset", old,
                          old, "agent state only: a frozen loop's gains are not published")
            )  # fmt: skip
            return None
        if mode == AUTO:
            (self.prev_kp[s], self.prev_ki[s]), (self.kp[s], self.ki[s]) = old, new
            self.pending[s] = True
        self.seq[s] += 1
        self._gains_dirty.add(s)
        self._audit.append(
            audit_row(loop_id, wall, t, int(self.seq[s]), MODE_VALUES[mode], "reset", old, new)
        )
        return StepResult(
            [loop_id],
            np.array([0.0 if t is None else t]),
            self.seq[[s]].copy(),
            self.mode[[s]].copy(),
            np.array([old]),
            np.array([new]),
            np.array([new]),
            [self.gateways[s]],
            UpdateReason.reset,
        )

    # -- samples ----------------------------------------------------------------------
    def _quiet(self, s, t):
        """Where the excitation gate is on and its window had closed by sample time ``t``
        (``s``, ``t``: one slot and time, or aligned arrays)."""
        return (self.exc_window[s] < math.inf) & (t > self.excited_until[s])

    def _new_clock(self, s: int, t: float) -> bool:
        """Count a run of consistent out-of-order samples; True when it is a new clock."""
        run = self.back_n[s] + 1.0 if self.back_n[s] and t > self.back_t[s] else 1.0
        self.back_t[s] = t
        self.back_n[s] = 0.0 if run >= CLOCK_RESET_SAMPLES else run
        return run >= CLOCK_RESET_SAMPLES

    def ingest(
        self, slots: np.ndarray, rows: Columns, wall: float
    ) -> tuple[np.ndarray, list[tuple[int, RejectReason, str]]]:
        """Take decoded samples of *distinct* loops (``slots`` aligned with ``rows``).

        The one implementation of the sample rules, vectorised: flood limit, duplicate and
        out-of-order times (or a new plant clock), absurd errors, adoption of reported
        gains, the excitation gate, the error integral and decimation to the RL period.
        Returns (mask of the loops now due for an RL step, rejections as (row, reason,
        detail)); a rejected sample changes nothing of its loop but its counters.
        """
        cols = {k: getattr(rows, k) for k in ("t", "e", "sp", "kp", "ki", "auto", "saturated")}
        t, e = cols["t"], cols["e"]
        tokens = np.minimum(
            self.burst, self.tokens[slots] + (wall - self.token_wall[slots]) * self.rate
        )
        self.token_wall[slots] = wall
        flood = tokens < 1.0
        self.tokens[slots] = np.where(flood, tokens, tokens - 1.0)
        last_t = self.last_t[slots]
        dup = ~flood & (t == last_t)
        late = ~flood & (t < last_t)
        for i in np.flatnonzero(late).tolist():  # rare: a new plant clock, or rejected
            if self._new_clock(int(slots[i]), float(t[i])):
                late[i] = False
                last_t[i] = math.nan
        absurd = ~(flood | dup | late) & (np.abs(e) * self.e_scale[slots] > MAX_AGENT_ERROR)
        ok = ~(flood | dup | late | absurd)
        rejections: list[tuple[int, RejectReason, str]] = []
        if not ok.all():
            for i in np.flatnonzero(~ok).tolist():
                if flood[i]:
                    rejections.append((i, RejectReason.flood, f"over {self.rate:g} samples/s"))
                elif dup[i]:
                    rejections.append((i, RejectReason.duplicate, f"t={t[i]} again"))
                elif late[i]:
                    rejections.append(
                        (i, RejectReason.out_of_order, f"t={t[i]} < last t={last_t[i]}")
                    )
                else:
                    detail = f"|e|={abs(e[i]):g} is absurd for this loop"
                    rejections.append((i, RejectReason.out_of_range, detail))
            slots, last_t, t, e = slots[ok], last_t[ok], t[ok], e[ok]
            cols = {k: v[ok] for k, v in cols.items()}
        self.back_n[slots] = 0.0
        self._adopt(slots, cols, wall)
        self._excite(slots, cols, last_t)

        self.n_samples[slots] += 1
        self.last_wall[slots] = wall
        auto, saturated = cols["auto"], cols["saturated"]
        paused = ~auto | saturated
        resumed = (self.manual[slots] | self.saturated[slots]) & ~paused
        self.manual[slots] = ~auto
        self.saturated[slots] = saturated
        self.last_t[slots] = t
        fresh = np.isnan(last_t) | (t - last_t > self.stale_gap[slots]) | resumed
        period = self.period[slots]
        next_due = np.where(fresh, t + period, self.next_due[slots])
        step = np.where(fresh | paused, 0.0, 0.5 * (e + self.last_e[slots]) * (t - last_t))
        self.int_e[slots] += step * self.int_scale[slots]
        self.last_e[slots] = e
        reached = t >= next_due
        next_due[reached] += period[reached] * (
            np.floor((t[reached] - next_due[reached]) / period[reached]) + 1.0
        )
        self.next_due[slots] = next_due
        due_ok = reached & (self.mode[slots] != FROZEN) & auto & ~saturated
        quiet = due_ok & self._quiet(slots, t)
        self.n_quiet[slots[quiet]] += 1
        due_ok &= ~quiet
        due = np.zeros(ok.size, bool)
        due[np.flatnonzero(ok)[due_ok]] = True
        return due, rejections

    def _excite(self, slots: np.ndarray, cols: dict[str, np.ndarray], last_t) -> None:
        """The excitation gate's part of :meth:`ingest` (before ``last_e`` moves on)."""
        sp, e, step = cols["sp"], cols["e"], self.exc_step[slots]
        ref = self.sp_ref[slots]
        has_sp = ~np.isnan(sp)
        with np.errstate(invalid="ignore"):  # NaN references compare False
            moved = np.where(
                has_sp,
                np.abs(sp - ref) >= step,
                ~np.isnan(last_t) & (np.abs(e - self.last_e[slots]) >= step),
            )
        self.sp_ref[slots] = np.where(has_sp & (moved | np.isnan(ref)), sp, ref)
        self.excited_until[slots[moved]] = cols["t"][moved] + self.exc_window[slots[moved]]

    def _adopt(self, slots: np.ndarray, cols: dict[str, np.ndarray], wall: float) -> None:
        has_kp, has_ki = ~np.isnan(cols["kp"]), ~np.isnan(cols["ki"])
        report = has_kp | has_ki
        if not report.any():
            return
        slots, has_kp, has_ki = slots[report], has_kp[report], has_ki[report]
        cur_kp, cur_ki = self.kp[slots], self.ki[slots]
        kp = np.where(has_kp, cols["kp"][report], cur_kp)
        ki = np.where(has_ki, cols["ki"][report], cur_ki)
        same = _close(kp, cur_kp) & _close(ki, cur_ki)
        in_flight = (
            ~same
            & self.pending[slots]
            & _close(kp, self.prev_kp[slots])
            & _close(ki, self.prev_ki[slots])
        )
        self.pending[slots[~in_flight]] = False
        changed = np.flatnonzero(~same & ~in_flight)
        if not changed.size:
            return
        t = cols["t"][report]
        for i in changed.tolist():
            s = int(slots[i])
            old = (self.kp[s], self.ki[s])
            self.kp[s], self.ki[s] = kp[i], ki[i]
            self._gains_dirty.add(s)
            self._audit.append(
                audit_row(
                    self.ids[s], wall, float(t[i]), int(self.seq[s]), _MODES[self.mode[s]].value,
                    "adopted", old, (float(kp[i]), float(ki[i])), "gains reported by the gateway",
                )
            )  # fmt: skip

    # -- RL step ----------------------------------------------------------------------
    def step(self, slots: np.ndarray, wall: float) -> StepResult:
        """One batched agent step of the loops in ``slots`` (each due, each once)."""
        kp_unit, ki_unit = self.kp_unit[slots], self.ki_unit[slots]
        old = np.column_stack([self.kp[slots], self.ki[slots]])
        obs = np.column_stack(
            [
                old[:, 0] / kp_unit,
                old[:, 1] / ki_unit,
                self.last_e[slots] * self.e_scale[slots],
                self.int_e[slots],
            ]
        )
        if self._policy is not None:
            state = self.hidden[slots]  # a contiguous copy, updated in place
            delta = self._policy.step_inplace(obs, state, self.forgetting[slots])
            self.hidden[slots] = state
        else:
            delta, self.hidden[slots] = self.agent.act(
                obs, self.hidden[slots], self.forgetting[slots]
            )
        proposed = np.column_stack(
            [(obs[:, 0] + delta[:, 0]) * kp_unit, (obs[:, 1] + delta[:, 1]) * ki_unit]
        )
        grow = 1.0 + self.max_rel[slots, None]
        lo = np.column_stack([self.kp_min[slots], self.ki_min[slots]])
        hi = np.column_stack([self.kp_max[slots], self.ki_max[slots]])
        new = np.clip(np.clip(proposed, lo, hi), old / grow, old * grow)

        auto = slots[self.mode[slots] == AUTO]
        applied = self.mode[slots] == AUTO
        self.prev_kp[auto], self.prev_ki[auto] = old[applied, 0], old[applied, 1]
        self.kp[auto], self.ki[auto] = new[applied, 0], new[applied, 1]
        self.pending[auto] = True
        self.seq[slots] += 1
        self.n_steps[slots] += 1
        self.n_updates[slots] += 1
        self._gains_dirty.update(slots.tolist())

        ids, gateways, listed = self.ids, self.gateways, slots.tolist()
        result = StepResult(
            [ids[s] for s in listed],
            self.last_t[slots],
            self.seq[slots],
            self.mode[slots],
            old,
            proposed,
            new,
            [gateways[s] for s in listed],
        )
        limited = np.flatnonzero(~np.isclose(proposed, new, rtol=GAIN_RTOL, atol=0.0).all(axis=1))
        details = [""] * len(slots)
        # formatting Python floats, not numpy scalars: a cold loop is limited in most steps
        for i, (kp, ki) in zip(limited.tolist(), proposed[limited].tolist(), strict=True):
            details[i] = _guard_detail(kp, ki)
        mode_names = [MODE_VALUES[c] for c in result.mode.tolist()]
        self._audit.extend(
            zip(
                result.loop_ids, [wall] * len(slots), result.t.tolist(), result.seq.tolist(),
                mode_names, ["agent"] * len(slots), old[:, 0].tolist(), old[:, 1].tolist(),
                new[:, 0].tolist(), new[:, 1].tolist(), details, strict=True,
            )
        )  # fmt: skip
        return result

    # -- persistence ------------------------------------------------------------------
    def drain_changes(self) -> tuple[list[tuple[float, float, int, str]], list[AuditRow]]:
        """Gains rows (kp, ki, seq, id) and audit rows accumulated since the last call."""
        dirty = np.array(sorted(self._gains_dirty), np.int64)
        ids = self.ids
        gains = list(
            zip(
                self.kp[dirty].tolist(), self.ki[dirty].tolist(), self.seq[dirty].tolist(),
                [ids[s] for s in dirty.tolist()], strict=True,
            )
        )  # fmt: skip
        audit, self._audit = self._audit, []
        self._gains_dirty.clear()
        return gains, audit

    def requeue(self, gains: list[tuple[float, float, int, str]], audit: list[AuditRow]) -> None:
        """Put back changes :meth:`drain_changes` returned that could not be stored, ahead
        of any newer ones (a deleted loop's gains row is dropped: its row is gone too)."""
        self._gains_dirty.update(self.slot_of[g[3]] for g in gains if g[3] in self.slot_of)
        self._audit[:0] = audit

    def snapshot(self, loop_ids: Iterable[str] | None = None) -> list[tuple[str, bytes, str]]:
        """(id, hidden state bytes, runtime JSON) of every loop (or of the given, if still
        registered)."""
        if loop_ids is None:
            items = self.slot_of.items()
        else:
            items = [(i, self.slot_of[i]) for i in loop_ids if i in self.slot_of]
        return [(loop_id, self.hidden[s].tobytes(), self._runtime(s)) for loop_id, s in items]

    def _runtime(self, s: int) -> str:
        def num(x: float) -> float | None:  # JSON has no NaN or inf
            return float(x) if math.isfinite(x) else None

        return orjson.dumps(
            {
                "last_t": num(self.last_t[s]),
                "last_e": float(self.last_e[s]),
                "int_e": float(self.int_e[s]),
                "next_due": num(self.next_due[s]),
                "sp_ref": num(self.sp_ref[s]),
                "excited_until": num(self.excited_until[s]),
                "manual": bool(self.manual[s]),
                "saturated": bool(self.saturated[s]),
                "counters": [int(getattr(self, n)[s]) for n in _I64[2:]],
            }
        ).decode()

    def _restore(self, s: int, hidden: bytes, runtime: str) -> None:
        h = np.frombuffer(hidden, np.float32)
        if h.size == self.hidden[s].size:
            self.hidden[s] = h.reshape(self.hidden[s].shape)
        rt = json.loads(runtime)
        self.last_t[s] = math.nan if rt["last_t"] is None else rt["last_t"]
        self.next_due[s] = math.nan if rt["next_due"] is None else rt["next_due"]
        self.last_e[s], self.int_e[s] = rt["last_e"], rt["int_e"]
        self.manual[s], self.saturated[s] = rt["manual"], rt["saturated"]
        sp_ref = rt.get("sp_ref")  # absent in snapshots from before the excitation gate
        self.sp_ref[s] = math.nan if sp_ref is None else sp_ref
        until = rt.get("excited_until")
        self.excited_until[s] = -math.inf if until is None else until
        # snapshots from before a counter was added list fewer: those stay 0
        for name, value in zip(_I64[2:], rt["counters"], strict=False):
            getattr(self, name)[s] = value

    # -- views ------------------------------------------------------------------------
    def status(self, s: int, wall: float) -> LoopStatus:
        return STATUSES[int(self.statuses(np.array([s]), wall)[0])]

    def statuses(self, slots: np.ndarray, wall: float) -> np.ndarray:
        """Each loop's :class:`LoopStatus` as an index into :data:`STATUSES`: the first
        condition that holds, in this order of precedence."""
        t = self.last_t[slots]
        conditions = [
            self.mode[slots] == FROZEN,
            np.isnan(t),
            wall - self.last_wall[slots] > self.stale_gap[slots],
            self.manual[slots],
            self.saturated[slots],
            self._quiet(slots, t),  # NaN t: False, and waiting comes first
            np.ones(slots.size, bool),
        ]
        return np.argmax(np.stack(conditions), axis=0)

    def view(self, loop_id: str, wall: float) -> LoopView:
        return self.raw_view(loop_id, wall).parse()

    def raw_view(self, loop_id: str, wall: float) -> RawView:
        """What :meth:`view` shows, copied but not parsed: the admin API parses it outside
        the lock (parsing 10,000 configs takes most of a second)."""
        s = self.slot(loop_id)
        return RawView(
            self.configs.raw(loop_id),
            float(self.kp[s]),
            float(self.ki[s]),
            self.status(s, wall),
            int(self.seq[s]),
            None if math.isnan(self.last_t[s]) else float(self.last_t[s]),
            float(self.int_e[s]),
            float(np.linalg.norm(self.hidden[s])),
            Counters(
                samples=int(self.n_samples[s]),
                rejected=int(self.n_rejected[s]),
                steps=int(self.n_steps[s]),
                updates=int(self.n_updates[s]),
                quiet=int(self.n_quiet[s]),
            ),
        )

    def status_counts(self, wall: float) -> dict[LoopStatus, int]:
        """How many loops are in each :meth:`status`."""
        used = np.fromiter(self.slot_of.values(), np.int64, len(self.slot_of))
        counts = np.bincount(self.statuses(used, wall), minlength=len(STATUSES))
        return {status: int(n) for status, n in zip(STATUSES, counts.tolist(), strict=True)}

    def mode_counts(self) -> dict[Mode, int]:
        used = np.fromiter(self.slot_of.values(), np.int64, len(self.slot_of))
        counts = np.bincount(self.mode[used], minlength=len(_MODES))
        return {mode: int(counts[_CODE[mode]]) for mode in Mode}


def _close(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(a - b) <= GAIN_RTOL * np.maximum(np.abs(a), np.abs(b))


def _guard_detail(kp: float, ki: float) -> str:
    return f"limited by the safety guard (proposed kp={kp:.6g}, ki={ki:.6g})"
