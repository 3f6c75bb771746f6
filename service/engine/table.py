"""Per-loop runtime state of the engine, kept in numpy arrays indexed by a loop's slot.

:class:`LoopTable` holds the state and its life cycle: registration, configuration,
reset, snapshot and restore, and the views of it (status, counters). The rules that
change it live beside it: :mod:`service.engine.rules` takes samples (the sample rules,
the excitation gate, integration and decimation), :mod:`service.engine.stepping` steps
due loops through the agent and the safety guard.

Every method must be called with :attr:`LoopTable.lock` held (the engine's methods take
it); changes to persist (new gains, audit rows) accumulate until
:meth:`LoopTable.drain_changes`.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterable, Sequence
from typing import Literal

import numpy as np

from service.agent.fast import FastPolicy, Precision
from service.agent.model import Agent
from service.engine import (
    fit_budget,
    monitor,
    op_law,
    output_limit,
    recorder,
    refusals,
    reported,
    resets,
    settings,
    status,
    steady,
    track,
    verify,
    views,
    watch,
)  # fmt: skip
from service.engine.audit import AuditRow
from service.engine.config import Configs, LoopConfig, LoopView
from service.engine.figures import Refused
from service.engine.id_state import IdState
from service.engine.modes import _CODE, _MODES
from service.engine.plant_hold import RELEASED
from service.engine.saved import Saved, restore_runtimes, runtimes_of
from service.engine.site import SiteDefaults
from service.engine.status import STATUSES
from service.engine.updates import StepResult
from service.units import Scaling
from service.wire import flood
from service.wire.protocol import LoopStatus, Mode

_F64 = (
    # gains now, registered, replaced by an update in flight; seq of the last auto update
    "kp", "ki", "reg_kp", "reg_ki", "prev_kp", "prev_ki", "auto_seq",
    # unit mapping (engineering per agent) and timing
    "kp_unit", "ki_unit", "e_scale", "int_scale", "period", "stale_gap", "forgetting",
    # the rest of the scaling in force (NaN: none; e_scale is above): three floats
    # instead of a Scaling object per loop (~0.5 KB of Python objects each)
    "u_scale", "time_unit",
    # controller action: +1 reverse, -1 direct (rules.ingest negates e and sp by it);
    # episode state
    "sign", "last_t", "last_e", "int_e", "next_due", "last_wall",
    # the agent's error observation (service.units.error_window): the window's running
    # sum and count, the end of the RL period they belong to, the mean at its end
    "win_sum", "win_n", "win_due", "obs_e",
    # safety guard and flood limiter; noise damping of the agent's steps (sigmas, 0: off)
    # and the robustness guard's largest sensitivity (0: off)
    "kp_min", "kp_max", "ki_min", "ki_max", "max_rel", "tokens", "token_wall", "damp",
    "ms_max",
    # settling (service.engine.stepping): the setting, the agent's steps in the episode and
    # the decayed sum of the log changes it asked for, kp and ki
    "settle", "settle_n", "settle_kp", "settle_ki",
    # the model check's factor (service.engine.model_check; 0: off) and the plant time its
    # run of held steps began (NaN: the last step was not held; views.hold)
    "mc_factor", "mc_since",
    # excitation gate: smallest setpoint step (engineering units), window after one (s;
    # inf: gate off), setpoint at the last step, end of the current window
    "exc_step", "exc_window", "sp_ref", "excited_until",
    # observation gain: the paper's move (2 agent units) over the last move's size, from
    # the setpoint before a run of moves (units.track_moves), the time of the last move;
    # the ramp rule's (units.ramp_rule) last setpoint, way of and samples since its last
    # change, the times of the last change that continued a ramp and of a ramp's first
    "obs_gain", "sp_anchor", "move_t", "sp_last", "sp_way", "sp_since", "ramp_t", "ramp_from",
    # run of out-of-order samples that may be a new clock: length and last t
    "back_n", "back_t",
    # identification (service.engine.watch): the reconstructed PI's integral term and the
    # kp it was last computed with, the last sample seen, the setpoint last seen
    "op_int", "op_kp", "prev_t", "prev_sp", "prev_pv", "prev_op", "id_sp",
)  # fmt: skip
_I64 = [
    "mode", "seq", "n_samples", "n_rejected", "n_steps", "n_updates", "n_quiet", "n_faults",
    "n_identified", "n_mismatch", "n_envelope", "n_model_holds", "n_osc_pauses", "n_held",
]  # fmt: skip
"""Mode, seq, then the counters (persisted in this order: new ones go at the end)."""
_COUNTERS = _I64[2:]
"""The counters a snapshot keeps, in this order (a new one goes at the end)."""
_REC = ["rec", "rec_n", "rec_k", "rec_stride", "rec_m", "rec_ev"]
"""Identification recorder: pool row (-1: not recording), rows held, samples since the
last move, the segment's coarsest row (samples), samples in the last row, the running
event's first row (service.engine.watch)."""
_MOVES = [name for name in _I64 if name not in ("mode", "n_samples", "n_rejected")]
"""What grows when a loop's state changes more than its samples' running sums do (a
step, an update, a model, a pause; seq): with the mode, :meth:`LoopTable._moves`."""
_BOOL = [
    "pending", "manual", "saturated",
    # identification: it runs, a scaling is in force, flagged, paused, last sample usable, op
    "watch", "scaled", "mismatch", "out_env", "prev_ok", "env_guard", "prev_meas",
]  # fmt: skip


class LoopTable:
    """Runtime state of all registered loops; one batched agent per table."""

    def __init__(
        self,
        agent: Agent,
        *,
        max_rate_hz: float,
        capacity: int = 64,
        inference_workers: int = 1,
        inference_precision: Precision | Literal["reference"] = "float32",
        site: SiteDefaults | None = None,
    ) -> None:
        self.agent = agent
        self.site = site or SiteDefaults()
        """What loops that leave guard.identify or guard.auto_rescale unset get."""
        self.fits = fit_budget.FitBudget(self.site.fit_share)
        # the allocation-free equivalent of agent.act; "reference" (and any object that
        # is not an Agent) steps with the agent's own act
        self._policy = (
            FastPolicy(agent, workers=inference_workers, precision=inference_precision)
            if isinstance(agent, Agent) and inference_precision != "reference"
            else None
        )
        self.inference_precision = self._policy.precision if self._policy else "agent.act"
        self.lock = threading.RLock()
        self.rate = float(max_rate_hz)
        self.burst = flood.burst(self.rate)
        self.configs = Configs()
        self.slot_of: dict[str, int] = {}
        self.ids: list[str | None] = []
        self.version = 0
        """Bumped whenever a loop is added or removed (slots remembered elsewhere, as the
        daemon's :class:`~service.daemon.slotmemo.SlotMemo`, are stale after it)."""
        self.gateways = np.empty(0, object)
        """Each slot's gateway (an interned str) or None: an array, so that a batch's loops
        are checked against their gateway in one comparison."""
        self._free: list[int] = []
        self._gains_dirty: set[int] = set()
        self._verify_dirty: set[int] = set()
        """Loops whose verification state moved: to snapshot before publishing."""
        self._audit: list[AuditRow] = []
        self.clock: Callable[[], float] | None = None  # step-free: service.engine.steady
        self.monitoring = True
        """False: no figures, no oscillation detector, hence no verdicts (benchmarks only:
        the setting ``monitoring`` measures what they cost)."""
        self.verifying = True
        """False: no verdicts and no oscillation pause (the figures are still computed):
        ``pitune evaluate`` measures the agent itself."""
        self.to_judge: list[tuple[np.ndarray, np.ndarray]] = []
        """(responses completed, oscillations started) awaiting :func:`verify.judge`."""
        self.decided: list[StepResult] = []  # model tunings made taking samples: to publish
        self.warming: list = []  # model tunings waiting for a warm run (first_tuning.flush)
        self.refuted: list[int] = []  # models refuted by verify.fail: TuningEngine._judge
        self.refused: dict[int, Refused] = {}  # by slot: the last samples refused (views)
        self.warm_run: tuple | None = None  # the batch under way: slots, keys, WarmRun
        self.mc_turn = 0
        """Where the model check's rotation over the loops to check starts
        (:data:`service.engine.model_check.PER_PASS`)."""
        self.ident: list[IdState | None] = []
        self.hold = RELEASED  # the plant-wide hold (service.engine.plant_hold)
        self.recorder = recorder.Recorder()
        self._allocate(capacity)

    # -- storage ----------------------------------------------------------------------
    def _allocate(self, capacity: int) -> None:
        old = len(self.ids)
        layers, hidden = self.agent.cfg.layers, self.agent.cfg.hidden
        for names, dtype in (
            (_F64, np.float64), (_I64, np.int64), (_REC, np.int64), (["snap_moves"], np.int64),
            (_BOOL, bool),
            (verify.F64, np.float64), (verify.F32, np.float32),
            (output_limit.F64, np.float64), (output_limit.BOOL, bool), (reported.F64, np.float64),
            (op_law.F64, np.float64),
        ):  # fmt: skip
            for name in names:
                arr = np.zeros(capacity, dtype)
                if old:
                    arr[:old] = getattr(self, name)
                setattr(self, name, arr)
        monitor.allocate(self, capacity, old)
        refusals.allocate(self, capacity, old)
        h = np.zeros((capacity, layers, hidden), np.float32)
        if old:
            h[:old] = self.hidden
        self.hidden = h
        self.ids.extend([None] * (capacity - old))
        gateways = np.full(capacity, None, object)
        gateways[:old] = self.gateways
        self.gateways = gateways
        self.ident.extend([None] * (capacity - old))
        self._free.extend(range(capacity - 1, old - 1, -1))

    def reserve(self, n: int) -> None:
        """Room for ``n`` more loops. The table grows by a quarter at least (amortised
        copies), to exactly the room asked for if that is more: a bulk registration gets
        no slack beyond it (slack of the per-loop arrays, ~2 KB a slot, is resident:
        the allocator hands out zeroed pages it reuses)."""
        if n > len(self._free):
            cap = len(self.ids)
            self._allocate(max(cap + n - len(self._free), cap + cap // 4 + 1))

    def _pop_free(self, n: int) -> list[int]:
        """The next ``n`` free slots, in the order ``self._free.pop()`` gives them."""
        picked = self._free[len(self._free) - n :][::-1]
        del self._free[len(self._free) - n :]
        return picked

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
        saved: Saved | None = None,
        wall: float,
    ) -> int:
        """Register a loop (new: registered gains; restored: stored gains and snapshot,
        as stored, ``hidden`` and ``runtime``, or parsed ahead, ``saved``)."""
        if saved is None and hidden is not None and runtime is not None:
            saved = Saved.parse(hidden, runtime)
        slots = self.add_many(
            [config], kp=None if kp is None else [kp], ki=None if ki is None else [ki],
            seq=[seq], saved=[saved], wall=wall,
        )  # fmt: skip
        return int(slots[0])

    def add_many(
        self,
        configs: Sequence[LoopConfig],
        *,
        kp: Sequence[float] | None = None,
        ki: Sequence[float] | None = None,
        seq: Sequence[int] | None = None,
        saved: Sequence[Saved | None] | None = None,
        wall: float,
    ) -> np.ndarray:
        """Register loops (aligned sequences; None: registered gains, seq 0, no snapshot)
        with one numpy assignment per array: the same slots and state as :meth:`add`
        one loop at a time, in order (a failover inserts 75,000 loops: ~0.2 ms a loop
        one by one). KeyError, and nothing changed, if an id is registered already or
        given twice. Returns the (n,) slots."""
        n = len(configs)
        ids = [c.id for c in configs]
        taken = [i for i in ids if i in self.slot_of]
        if taken or len(set(ids)) < n:
            dup = taken[0] if taken else next(i for i in ids if ids.count(i) > 1)
            raise KeyError(f"loop {dup!r} already registered")
        picked = self._pop_free(min(n, len(self._free)))
        if len(picked) < n:  # (one growth, to the room asked for: add() grows in steps)
            self.reserve(n - len(picked))
            picked += self._pop_free(n - len(picked))
        s = np.array(picked, np.int64)
        for loop_id, slot in zip(ids, picked, strict=True):
            self.ids[slot] = loop_id
            self.slot_of[loop_id] = slot
        self.version += n
        self.reg_kp[s] = [c.kp for c in configs]
        self.reg_ki[s] = [c.ki for c in configs]
        self.kp[s] = self.reg_kp[s] if kp is None else kp
        self.ki[s] = self.reg_ki[s] if ki is None else ki
        self.seq[s] = self.auto_seq[s] = 0 if seq is None else seq  # (unknown: the seq)
        for name in _COUNTERS:
            getattr(self, name)[s] = 0
        self.n_refused[s] = 0  # (by reason: refusals)
        self.tokens[s], self.token_wall[s] = self.burst, steady.now(self, wall)
        saved = [None] * n if saved is None else saved
        # a restored identification first: the configuration follows its scaling
        for slot, x in zip(picked, saved, strict=True):
            self.ident[slot] = IdState() if x is None or x.ident is None else x.ident
        for name, value in zip(_REC, (-1, 0, 0, 1, 0, 0), strict=True):
            getattr(self, name)[s] = value
        self.mismatch[s] = self.out_env[s] = self.prev_ok[s] = self.prev_meas[s] = False
        self.op_int[s] = self.op_kp[s] = 0.0
        self.prev_t[s] = self.prev_sp[s] = self.prev_pv[s] = self.prev_op[s] = math.nan
        self.id_sp[s] = math.nan
        monitor.clear(self, s)
        output_limit.clear(self, s)
        op_law.clear(self, s)
        verify.init(self, s)
        settings.configure(self, s, configs)
        self._restart(s)
        restoring = [i for i, x in enumerate(saved) if x is not None]
        restore_runtimes(self, s[restoring], [saved[i] for i in restoring], _COUNTERS)
        # the store holds this state (the snapshot restored, or no row: as registered)
        self.snap_moves[s] = self._moves(s)
        return s

    def scaling_of(self, s: int) -> Scaling | None:
        """The scaling in force: identified, else the config's hint, else None (built
        from the arrays: its factors were validated when it was put in force)."""
        if not self.scaled[s]:
            return None
        return Scaling.model_construct(
            e_scale=float(self.e_scale[s]),
            u_scale=float(self.u_scale[s]),
            time_unit_s=float(self.time_unit[s]),
        )

    def _restart(self, s) -> None:
        """A fresh episode: zero hidden state and integral, no time reference (``s``: a
        slot or an array of them)."""
        self.hidden[s] = 0.0
        self.int_e[s] = self.last_e[s] = self.obs_e[s] = 0.0
        self.last_t[s] = self.next_due[s] = self.sp_ref[s] = self.win_due[s] = math.nan
        self.excited_until[s] = self.move_t[s] = self.ramp_t[s] = self.ramp_from[s] = -math.inf
        self.sp_last[s], self.sp_way[s], self.sp_since[s] = math.nan, math.nan, 0.0
        self.obs_gain[s], self.sp_anchor[s], self.mc_since[s] = 1.0, math.nan, math.nan
        self.back_n[s], self.last_wall[s] = 0.0, -math.inf  # (last_wall: steady.now's clock)
        self.pending[s] = self.manual[s] = self.saturated[s] = False
        output_limit.end_runs(self, s)
        self.unsettle(s)

    def unsettle(self, s) -> None:
        """The agent's steps at full size again: a new episode (``guard.settle_steps``)."""
        self.settle_n[s] = self.settle_kp[s] = self.settle_ki[s] = 0.0

    def reconfigure(self, config: LoopConfig) -> None:
        s = self.slot(config.id)
        if _CODE[config.mode] != self.mode[s]:  # a proposal belongs to the mode it was made in
            track.restart(self, s)
            # and so does settling: in shadow or advisory the agent's asks are not applied
            self.unsettle(s)
        settings.configure(self, np.array([s]), [config])

    def remove(self, loop_id: str) -> None:
        s = self.slot_of[loop_id]
        watch.stop(self, s)
        self.ident[s] = None
        del self.slot_of[loop_id]
        del self.configs[loop_id]
        self.refused.pop(s, None)
        self.ids[s] = None
        self.version += 1
        self._gains_dirty.discard(s)
        self._free.append(s)

    def reset(self, loop_id: str, wall: float, actor: str = "") -> StepResult | None:
        """A fresh episode and the registered gains; the result is to be published.

        The gains move as an agent step's would: an ``auto`` loop takes them at once, as
        an update in flight (the gateway's next samples still report the old gains, which
        must not be adopted back); an ``advisory`` loop's are a proposal (reason
        ``reset``, replacing the one pending) that its gains follow when it is accepted
        (:mod:`service.engine.resets`). A ``frozen`` loop gets no gains messages, so only
        its episode restarts and its gains stay those in force: None, nothing to publish.

        The update's ``t`` is the plant time of the newest sample accepted since the
        registration or the last reset (0.0 if none: docs/protocol.md, Gains). ``actor``
        (who reset, when known) is recorded as ``actor=<actor>`` in the audit row's detail,
        after any other text with ``"; "``.
        """
        return resets.reset(self, self.slot(loop_id), wall, actor)

    # -- samples ----------------------------------------------------------------------
    def gate_closed(self, s, t):
        """Where the excitation gate is on and its window had closed by sample time ``t``
        (``s``, ``t``: one slot and time, or aligned arrays)."""
        return (self.exc_window[s] < math.inf) & (t > self.excited_until[s])

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

    def drain_verify_dirty(self) -> list[str]:
        """Ids of the loops whose verification state moved since the last call (the
        daemon snapshots them before publishing)."""
        ids = [self.ids[s] for s in sorted(self._verify_dirty) if self.ids[s] is not None]
        self._verify_dirty.clear()
        return ids

    def requeue_verify_dirty(self, ids: list[str]) -> None:
        self._verify_dirty.update(self.slot_of[i] for i in ids if i in self.slot_of)

    def snapshot_turn(self, turn: int, every: int) -> list[str]:
        """The loops a periodic snapshot's ``turn`` writes: each whose state moved beyond
        its samples' running sums since its last snapshot (:data:`_MOVES`), and the
        others in rotation, each at least every ``every`` turns."""
        used = np.fromiter(self.slot_of.values(), np.int64, len(self.slot_of))
        moved = self._moves(used) != self.snap_moves[used]
        picked = used[moved | ((used + turn) % every == 0)]
        ids = self.ids
        return [ids[s] for s in picked.tolist()]

    def _moves(self, slots: np.ndarray) -> np.ndarray:
        """One number that changes exactly when one of :data:`_MOVES` (they only grow:
        their sum) or the mode (which may go either way) does."""
        grown = sum(getattr(self, name)[slots] for name in _MOVES)
        return grown * len(_MODES) + self.mode[slots]

    def requeue(self, gains: list[tuple[float, float, int, str]], audit: list[AuditRow]) -> None:
        """Put back changes :meth:`drain_changes` returned that could not be stored, ahead
        of any newer ones (a deleted loop's gains row is dropped: its row is gone too)."""
        self._gains_dirty.update(self.slot_of[g[3]] for g in gains if g[3] in self.slot_of)
        self._audit[:0] = audit

    def snapshot(self, loop_ids: Iterable[str] | None = None) -> list[tuple[str, bytes, str]]:
        """(id, hidden state bytes, runtime JSON) of every loop (or of the given, if still
        registered)."""
        if loop_ids is None:
            items = list(self.slot_of.items())
        else:
            items = [(i, self.slot_of[i]) for i in loop_ids if i in self.slot_of]
        slots = np.fromiter((s for _, s in items), np.int64, len(items))
        self.snap_moves[slots] = self._moves(slots)
        hidden = self.hidden[slots]
        runtimes = runtimes_of(self, slots, _COUNTERS)
        return [
            (loop_id, row.tobytes(), runtime)
            for (loop_id, _), row, runtime in zip(items, hidden, runtimes, strict=True)
        ]

    # -- views ------------------------------------------------------------------------
    def status(self, s: int, wall: float) -> LoopStatus:
        return STATUSES[int(self.statuses(np.array([s]), wall)[0])]

    def statuses(self, slots: np.ndarray, wall: float) -> np.ndarray:
        """Each loop's status, an index into :data:`STATUSES` (:mod:`.status`)."""
        return status.statuses(self, slots, wall)

    def view(self, loop_id: str, wall: float) -> LoopView:
        return self.raw_view(loop_id, wall).parse()

    def raw_view(self, loop_id: str, wall: float) -> views.RawView:
        """What :meth:`view` shows, copied but not parsed: the admin API parses it outside
        the lock (parsing 10,000 configs takes most of a second)."""
        return views.raw_view(self, self.slot(loop_id), self.configs.raw(loop_id), wall)

    def status_counts(self, wall: float) -> dict[LoopStatus, int]:
        """How many loops are in each :meth:`status`."""
        used = np.fromiter(self.slot_of.values(), np.int64, len(self.slot_of))
        counts = np.bincount(self.statuses(used, wall), minlength=len(STATUSES))
        return {status: int(n) for status, n in zip(STATUSES, counts.tolist(), strict=True)}

    def mode_counts(self) -> dict[Mode, int]:
        used = np.fromiter(self.slot_of.values(), np.int64, len(self.slot_of))
        counts = np.bincount(self.mode[used], minlength=len(_MODES))
        return {mode: int(counts[_CODE[mode]]) for mode in Mode}
