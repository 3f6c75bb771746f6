"""Views of a loop's arrays as the API shows them: the whole loop (:class:`RawView`,
its config still JSON), the monitor's and verification's figures
(:mod:`service.engine.figures`); called with the table's lock held."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from service.engine import box, monitor, oscillation, plant_hold, refusals, status, track, verify
from service.engine.config import Counters, LoopConfig, LoopView
from service.engine.fences import COOLED
from service.engine.figures import (
    Fence,
    Performance,
    Proposal,
    Refused,
    ResponseFigures,
    Verification,
    WindowFigures,
)  # fmt: skip
from service.engine.id_state import NO_SAMPLES
from service.engine.id_view import Identification
from service.engine.modes import ADVISORY
from service.engine.monitor import same_gains
from service.engine.updates import REASONS
from service.wire.protocol import Hold, UpdateReason

if TYPE_CHECKING:
    from service.engine.table import LoopTable
    from service.units import Scaling
    from service.wire.protocol import LoopStatus


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
    scaling: Scaling | None = None
    """The scaling in force (the hint's or the identified model's)."""
    identification: Identification | None = None
    verification: Verification | None = None
    proposal: Proposal | None = None
    hold: Hold | None = None
    oscillating: bool = False
    refused: Refused | None = None
    refused_counts: dict | None = None
    status_why: str | None = None

    def parse(self) -> LoopView:
        config = LoopConfig.model_validate_json(self.config)
        scaling = self.scaling
        return LoopView(
            config=config,
            scaling=scaling,
            rl_period_s=None if scaling is None else scaling.rl_period_s,
            identification=self.identification,
            mode=config.mode,
            kp=self.kp,
            ki=self.ki,
            status=self.status,
            status_why=self.status_why,
            seq=self.seq,
            last_sample_t=self.last_sample_t,
            int_e=self.int_e,
            hidden_norm=self.hidden_norm,
            counters=self.counters,
            verification=self.verification,
            proposal=self.proposal,
            hold=self.hold,
            oscillating=self.oscillating,
            refused=self.refused,
            refused_counts=self.refused_counts,
        )


def raw_view(tb: LoopTable, s: int, config: bytes, wall: float) -> RawView:
    """A loop's view with its config still JSON (``config``), copied from the table."""
    st = tb.status(s, wall)
    return RawView(
        config,
        float(tb.kp[s]),
        float(tb.ki[s]),
        st,
        int(tb.seq[s]),
        None if math.isnan(tb.last_t[s]) else float(tb.last_t[s]),
        float(tb.int_e[s]),
        float(np.linalg.norm(tb.hidden[s])),
        Counters(
            samples=int(tb.n_samples[s]),
            rejected=int(tb.n_rejected[s]),
            steps=int(tb.n_steps[s]),
            updates=int(tb.n_updates[s]),
            quiet=int(tb.n_quiet[s]),
            faults=int(tb.n_faults[s]),
            identified=int(tb.n_identified[s]),
            mismatches=int(tb.n_mismatch[s]),
            envelope_pauses=int(tb.n_envelope[s]),
            model_holds=int(tb.n_model_holds[s]),
            oscillation_pauses=int(tb.n_osc_pauses[s]),
            output_holds=int(tb.n_held[s]),
        ),
        scaling=tb.scaling_of(s),
        identification=identification(tb, s),
        verification=verification(tb, s),
        proposal=proposal(tb, s),
        hold=hold(tb, s),
        oscillating=bool(tb.o_osc[s]),
        status_why=status.why(tb, s, st, wall),
        refused=tb.refused.get(s),
        refused_counts=refusals.counts(tb, s),
    )


HOLDS = (None, "cooldown", "model_check", "plant")
"""A loop's hold (:class:`Hold`) by its code from :func:`holds` (0: none)."""


def cooling(tb: LoopTable, s):
    """Where the agent is held for the cool-down at the loop's last sample (``s`` a slot
    or slots): rules.ingest steps it again at the first due sample at or after it."""
    return tb.cool_until[s] > tb.last_t[s]


def holds(tb: LoopTable, s):
    """Each loop's hold as a code into :data:`HOLDS` (``s`` a slot or slots; vectorised
    for the console's overview): the plant-wide hold first (it holds every loop), then
    the cool-down (it holds every step), then a run of steps the model check held
    (``mc_since``, set by stepping.step)."""
    code = np.where(cooling(tb, s), 1, np.where(np.isnan(tb.mc_since[s]), 0, 2))
    return np.where(tb.hold.held, 3, code)


def hold(tb: LoopTable, s: int) -> Hold | None:
    """What holds the agent's steps of slot ``s`` that its status may not say."""
    guard = HOLDS[int(holds(tb, s))]
    if guard == "plant":
        return plant_hold.loop_hold(tb.hold)
    if guard == "cooldown":
        until = float(tb.cool_until[s])
        cause = COOLED.get(float(tb.cool_why[s]))
        after = (
            f"after {cause}"
            if cause
            else "after a change of the tuner's own, a rollback, "
            "a rejected proposal or a model's tuning until its verdict"
        )
        return Hold(guard=guard, until_t=until, why=(
            f"the agent is held until t = {until:.10g} (plant time): the cool-down {after} "
            "(guard.cooldown_periods; the audit log has the change)"
        ))  # fmt: skip
    if guard == "model_check":
        since = float(tb.mc_since[s])
        return Hold(guard=guard, since_t=since, why=(
            f"the model check has held the agent's steps since t = {since:.10g} (plant "
            "time): the identified model predicts the gains they proposed to track worse "
            "than guard.model_check times the model's tuning and worse than the gains in "
            "force (or deferred them: more loops due in one pass than it checks), which "
            "stay until a step passes (counters.model_holds; the audit rows with "
            "guard=model give the predictions)"
        ))  # fmt: skip
    return None


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def verification(tb: LoopTable, s: int) -> Verification:
    margin = _num(tb.v_margin[s])
    pending = bool(verify.changed(tb, s))
    return Verification(
        enabled=margin is not None,
        margin=margin,
        last_good_kp=float(tb.g_kp[s]),
        last_good_ki=float(tb.g_ki[s]),
        # the engine's figures are of the action-signed error (a direct-acting loop's is
        # mirrored, rules.py): up and down as the setpoint moved, for the user
        last_good_iae=_num((tb.g_iae if tb.sign[s] > 0 else tb.g_iae_dn)[s]),
        last_good_iae_down=_num((tb.g_iae_dn if tb.sign[s] > 0 else tb.g_iae)[s]),
        last_good_seq=int(tb.g_seq[s]),
        judged_seq=int(tb.v_seq[s]),
        pending=pending,
        held_until_t=_num(tb.cool_until[s]) if cooling(tb, s) else None,
        fence=_fence(tb, s),
        paused_until_t=_num(tb.osc_until[s]) if verify.paused(tb, s, tb.last_t[s]) else None,
        detune_floor_kp=_num(tb.o_kp[s]),
        detune_floor_ki=_num(tb.o_ki[s]),
        cut_short=int(tb.c_cut[s]),
        unsettled_moves=int(tb.c_early[s]),
        why=_waits(tb, s) if pending and margin is not None else None,
    )


def _waits(tb: LoopTable, s: int) -> str:
    """What the verdict of the change pending at slot ``s`` waits for."""
    span = monitor.RESPONSE_PERIODS * float(tb.period[s])
    v_seq = int(tb.v_seq[s])
    since = (
        f"the changes after seq {v_seq} (up to seq {int(tb.seq[s])})"
        if v_seq >= 0  # -1: an operator's change to the gains registered (seq 0)
        else f"the adopted gains (seq {int(tb.seq[s])})"
    )
    if math.isnan(span):  # no scaling: no RL period to judge a response over
        return (
            f"{since} wait for identification to put a model in force (the loop has no "
            "scaling yet: a response is judged over RL periods of its model), then for the "
            "next complete setpoint response. Next: move the setpoint in auto and let each "
            "response settle"
        )
    cut, early = int(tb.c_cut[s]), int(tb.c_early[s])
    window = f"{span:.4g} s ({monitor.RESPONSE_PERIODS:g} RL periods)"
    if not cut and not early:
        return (
            f"{since} wait for the next complete setpoint response: a move of at least "
            f"guard.excitation_min_step pv_scales on a settled loop, then {window} without "
            "another move"
        )
    parts = []
    if cut:
        last = float(tb.c_cut_s[s])
        parts.append(
            f"{cut} response{'s were' if cut > 1 else ' was'} cut short by the next move "
            f"(the last after {last:.4g} s of the {window} a response is judged over)"
        )
    if early:
        left, limit = 100 * float(tb.c_left[s]), 100 * monitor.SETTLED_AT_MOVE
        parts.append(
            f"{early} move{'s' if early > 1 else ''} opened none, the loop not settled from "
            f"the move before (the last found {left:.0f} % of its move left; a response "
            f"opens within {limit:.0f} % plus the noise)"
        )
    return (
        f"since the last complete setpoint response {' and '.join(parts)}: no change is "
        f"judged while the setpoint moves that often, and {since} wait for a verdict (a "
        f"rollback goes back to the last-good gains of seq {int(tb.g_seq[s])}). Next: let "
        f"the loop settle and the setpoint stand {span:.4g} s after a move now and then, or "
        "stop the automatic changes (PATCH mode advisory or frozen)"
    )


def _fence(tb: LoopTable, s: int) -> Fence | None:
    if not tb.x_until[s] > tb.last_t[s]:
        return None
    bounds = (_num(tb.x_kp_lo[s]), _num(tb.x_kp_hi[s]), _num(tb.x_ki_lo[s]), _num(tb.x_ki_hi[s]))
    return Fence(**dict(zip(("kp_min", "kp_max", "ki_min", "ki_max"), bounds, strict=True)),
                 until_t=float(tb.x_until[s]))  # fmt: skip


def proposal(tb: LoopTable, s: int) -> Proposal | None:
    if tb.mode[s] != ADVISORY or math.isnan(tb.adv_seq[s]):
        return None
    kp, ki = float(tb.adv_kp[s]), float(tb.adv_ki[s])
    code = float(tb.adv_why[s])  # the reason it was made for
    reason = REASONS.get(int(code)) if math.isfinite(code) else None
    if reason is None:  # none stored (a snapshot of before session 40), or a code of a
        # later version's (a snapshot restored by an older tuner): told from the gains
        back = bool(same_gains(kp, tb.g_kp[s]) & same_gains(ki, tb.g_ki[s]))
        reason = UpdateReason.rollback if back else UpdateReason.agent
    return Proposal(
        seq=int(tb.adv_seq[s]), kp=kp, ki=ki, dkp=kp - float(tb.kp[s]), dki=ki - float(tb.ki[s]),
        kp_in_force=float(tb.kp[s]), ki_in_force=float(tb.ki[s]), reason=reason.value,
        made_t=_num(float(tb.adv_t[s])), at_reach=track.at_reach(tb, s),
        refused=track.refusal(tb, s),
    )  # fmt: skip


def _response(row, unit: float | None) -> ResponseFigures:
    t, iae, over, rise, settle, mse = (_num(float(x)) for x in row)

    def tu(x: float | None) -> float | None:
        return None if x is None or not unit else x / unit

    return ResponseFigures(
        t=t or 0.0, iae=iae or 0.0, iae_tu=tu(iae), overshoot_pct=over or 0.0, rise_s=rise,
        rise_tu=tu(rise), settle_s=settle, settle_tu=tu(settle), mse=mse,
    )  # fmt: skip


def performance(tb: LoopTable, s: int) -> Performance:
    sc = tb.scaling_of(s)
    unit = None if sc is None else sc.time_unit_s
    hist = [_response(row, unit) for row in monitor.history(tb, s)]
    var = max(float(tb.w_sq[s] - tb.w_mean[s] ** 2), 0.0)
    return Performance(
        loop_id=tb.ids[s],
        time_unit_s=unit,
        last=hist[0] if hist else None,
        history=hist,
        window=WindowFigures(
            error_mean=float(tb.sign[s] * tb.w_mean[s]),  # sp - pv, not action-signed
            error_var=var,
            noise_sigma=float(oscillation.noise_sigma(tb, s, cold=True)),
            oscillation_index=_num(tb.o_index[s]) if tb.o_n[s] >= 2 else None,
            oscillating=bool(tb.o_osc[s]),
            manual_share=float(tb.w_manual[s]),
            saturated_share=float(tb.w_sat[s]),
            rejected_share=float(tb.w_rej[s]),
            output_held=float(tb.oh_op[s]) if tb.oh_held[s] else None,
            pv_stalled=bool(tb.ps_held[s]),
        ),  # fmt: skip
        verification=verification(tb, s),
    )


def monitor_summary(tb: LoopTable) -> tuple[dict[str, int], dict[str, float]]:
    """Counts and means over all loops for the metrics (vectorised: no per-loop series)."""
    used = np.fromiter(tb.slot_of.values(), np.int64, len(tb.slot_of))
    if not used.size:  # no loop (the last one deleted): no mean, not the last loop's
        return dict.fromkeys(_STATES, 0), dict.fromkeys(_FIGURES, math.nan)
    pending = verify.changed(tb, used)
    counts = {
        "oscillating": int(tb.o_osc[used].sum()),
        "output_held": int(tb.oh_held[used].sum()),
        "pv_stalled": int(tb.ps_held[used].sum()),
        "change_pending": int(pending.sum()),
        "held": int(cooling(tb, used).sum()),
        "proposal_pending": int(((tb.mode[used] == ADVISORY) & ~np.isnan(tb.adv_seq[used])).sum()),
    }
    ratio = tb.f_iae[used] / verify.reference(tb, used)
    ratio = ratio[np.isfinite(ratio)]
    means = {
        "manual_share": float(tb.w_manual[used].mean()),
        "saturated_share": float(tb.w_sat[used].mean()),
        "rejected_share": float(tb.w_rej[used].mean()),
        "iae_ratio": float(ratio.mean()) if ratio.size else math.nan,
    }
    return counts, means


_STATES = (
    "oscillating", "output_held", "pv_stalled", "change_pending", "held", "proposal_pending",
)  # fmt: skip
_FIGURES = ("manual_share", "saturated_share", "rejected_share", "iae_ratio")
"""The means of :func:`monitor_summary`: every one is set at each scrape."""


def identification(tb: LoopTable, s: int) -> Identification | None:
    """The loop's identification as the REST view shows it (:mod:`service.engine.watch`)."""
    st = tb.ident[s]
    if st is None:
        return None
    scaling = tb.scaling_of(s)
    state = "off" if not tb.watch[s] else "checking" if tb.scaled[s] else "identifying"
    why = (
        (st.why if tb.n_samples[s] else NO_SAMPLES)
        if tb.watch[s]
        else (
            "identification off (guard.identify; by default on, for hinted loops as the "
            "tuner's identify_hinted_loops says)"
        )
    )
    if s in tb.fits.owed:
        why = f"{why} (next assessment waiting for the identification budget)"
    model = st.model
    return Identification(
        state=state,
        why=why,
        model=None if model is None else model.as_dict(),
        in_force=None if st.in_force is None else st.in_force.as_dict(),
        in_force_t=st.in_force_t,
        apparent=None if model is None or scaling is None else box.apparent(scaling, model),
        events=[ev.as_dict() for ev in st.events],
        mismatch=bool(tb.mismatch[s]),
        out_of_envelope=bool(tb.out_env[s]),
        refuted=[r.model.as_dict() for r in st.refuted],
    )
