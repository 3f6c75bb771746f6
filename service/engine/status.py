"""A loop's status (:class:`LoopStatus`): the first of the conditions that holds, in an
order of precedence (what the safety guard is doing with the loop right now)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from service.engine import box, reported, steady, verify
from service.engine.modes import FROZEN
from service.units import AGENT_GAIN, AGENT_TAU
from service.wire.protocol import LoopStatus

if TYPE_CHECKING:
    from service.engine.table import LoopTable

STATUSES = [
    LoopStatus.frozen, LoopStatus.waiting, LoopStatus.stale, LoopStatus.gains_out_of_bounds,
    LoopStatus.identifying,
    LoopStatus.out_of_envelope, LoopStatus.manual, LoopStatus.saturated,
    LoopStatus.oscillating, LoopStatus.hint_mismatch, LoopStatus.quiet, LoopStatus.tuning,
]  # fmt: skip
"""Statuses in order of precedence (see :func:`statuses`)."""


def statuses(tb: LoopTable, slots: np.ndarray, wall: float) -> np.ndarray:
    """Each loop's :class:`LoopStatus` as an index into :data:`STATUSES`: the first
    condition that holds, in this order of precedence."""
    t = tb.last_t[slots]
    conditions = [
        tb.mode[slots] == FROZEN,
        np.isnan(t),
        steady.now(tb, wall) - tb.last_wall[slots] > tb.stale_gap[slots],
        reported.held(tb, slots),
        ~tb.scaled[slots],
        tb.out_env[slots],
        tb.manual[slots],
        tb.saturated[slots],
        verify.paused(tb, slots, t),
        tb.mismatch[slots],
        tb.gate_closed(slots, t),  # NaN t: False, and waiting comes first
        np.ones(slots.size, bool),
    ]
    return np.argmax(np.stack(conditions), axis=0)


def why(tb: LoopTable, s: int, status: LoopStatus, wall: float) -> str | None:
    """What holds a loop of any status but ``tuning`` (None for it), with the numbers,
    and the operator's next step: the view's ``status_why``."""
    return None if status == LoopStatus.tuning else _WHY[status](tb, s, wall)


def _g(x: float) -> str:
    return f"{x:.3g}"


def _frozen(tb, s, wall) -> str:
    return (
        "mode frozen: the tuner steps, proposes and publishes nothing for the loop. Next: "
        "PATCH mode auto (or advisory, shadow) to tune it again"
    )


def _waiting(tb, s, wall) -> str:
    return (
        "no sample received since the loop was registered (or reset). Next: check that its "
        "gateway runs and publishes samples for this loop id"
    )


def _stale(tb, s, wall) -> str:
    gap, limit = steady.now(tb, wall) - float(tb.last_wall[s]), float(tb.stale_gap[s])
    since = f"for {_g(gap)} s" if math.isfinite(gap) else "since the tuner started"
    return (
        f"no sample {since}, more than guard.stale_periods sample periods "
        f"({_g(limit)} s): tuning pauses. Next: check the gateway and its link to the DCS; "
        "tuning resumes with the next sample"
    )


def _out_of_bounds(tb, s, wall) -> str:
    return (
        f"the gateway reports kp = {_g(tb.a_kp[s])}, ki = {_g(tb.a_ki[s])}, outside the "
        f"guard's bounds (kp {_g(tb.c_kp_min[s])}..{_g(tb.c_kp_max[s])}, ki "
        f"{_g(tb.c_ki_min[s])}..{_g(tb.c_ki_max[s])}): tuning is held. Next: set gains within "
        "the bounds in the DCS, PATCH the bounds to hold them if they are meant, or reset the "
        "loop; check that the gateway reports ki per second, not an integral time"
    )


def _identifying(tb, s, wall) -> str:
    st = tb.ident[s]
    now = f" ({st.why})" if st is not None and st.why else ""
    return (
        f"no model hint: the tuner identifies the loop's model from its data and tunes it "
        f"once a model is confident{now}. Next: move the setpoint in auto, by at least a "
        "few times the measurement noise, and let each response settle"
    )


def _apparent(tb, s) -> dict[str, float] | None:
    """The latest model identified, else the one in force, in the agent's units (None:
    neither, or no scaling)."""
    st, sc = tb.ident[s], tb.scaling_of(s)
    m = None if st is None else st.model if st.model is not None else st.in_force
    return None if m is None or sc is None else box.apparent(sc, m)


def _seen(sc, app: dict[str, float]) -> str:
    """A model's apparent values (:func:`box.apparent`) seen back through the scaling in
    force ``sc`` (the one they were seen through: a new scaling ends a pause): the
    identified K and tau against the scaling's."""
    k_in_force = sc.u_scale / sc.e_scale * AGENT_GAIN
    tau_in_force = sc.time_unit_s * AGENT_TAU
    k, tau = app["gain"] / AGENT_GAIN * k_in_force, app["tau"] / AGENT_TAU * tau_in_force
    return (
        f"identified K = {_g(k)}, tau = {_g(tau)} s, theta = {_g(app['theta_ratio'] * tau)} "
        f"s against the scaling in force's K = {_g(k_in_force)} ({_g(k / k_in_force)}x), "
        f"tau = {_g(tau_in_force)} s ({_g(tau / tau_in_force)}x)"
    )


def _integrator(seen: dict) -> str:
    return (
        f"K = {_g(seen['k_per_s'])} PV units per output unit per second, dead time "
        f"{_g(seen['theta_s'])} s"
    )


def _out_of_envelope(tb, s, wall) -> str:
    """Named by the model that paused the loop (:attr:`IdState.paused_by
    <service.engine.id_state.IdState.paused_by>`), and the latest where it differs: the
    why gave the latest alone, which an unconfident model could put inside the ranges it
    called outside (session 41: gain 0.45 and tau 0.59 on a loop paused at gain 0.126)."""
    paused = tb.ident[s].paused_by
    later = _later(tb, s, paused)
    if paused is not None and paused.get("integrating"):
        return (
            f"the process looks integrating ({_integrator(paused)}; identified at t = "
            f"{paused['t']:.10g} s, plant time): the agent does not tune integrators and "
            f"tuning pauses{later}. Next: tune the loop by hand and freeze it (PATCH mode "
            "frozen), or POST /loops/{id}/identify if the process does not integrate"
        )
    leave, back = box.edges(), box.edges(box.RESUME_MARGIN)
    if paused is None:  # (paused before the tuner kept the model: a snapshot restored)
        which, where = "a model", " (the loop's out_of_envelope audit row has its numbers)"
    else:
        which = f"the model identified at t = {paused['t']:.10g} s (plant time)"
        seen = _seen(tb.scaling_of(s), paused)
        where = f"; in the agent's units: {_placed(paused, leave, back)}; {seen}"
    rescale = (
        "the hint is off: PATCH guard.auto_rescale true (the next confident model "
        "rescales the loop) or register it again with the identified K and tau as k_hat "
        "and tau_hat; "
        if tb.mismatch[s]
        else ""
    )
    th = _g(leave["theta_ratio"][1])
    return (
        f"{which} outside the agent's envelope ({_ranges(leave)}) paused tuning{where}"
        f"{later}. It resumes when a confident model lies within {_ranges(back)}. Next: "
        f"{rescale}after a change of the plant, POST /loops/{{id}}/identify; a process the "
        f"agent was not trained for (theta/tau beyond {th}): tune it by hand and freeze it "
        "(PATCH mode frozen)"
    )


def _later(tb, s, paused: dict | None) -> str:
    """The latest model, briefly, where it is not the one that paused the loop."""
    m, sc = tb.ident[s].model, tb.scaling_of(s)
    if m is None or sc is None:
        return ""
    seen = box.as_seen(sc, m)
    if paused is not None and seen == {k: v for k, v in paused.items() if k != "t"}:
        return ""
    what = (
        f"integrating, {_integrator(seen)}"
        if m.integrating
        else _placed(seen, box.edges(), box.edges(box.RESUME_MARGIN))
    )
    return (
        f"; the latest model{'' if paused is None else ' differs'}: {what}"
        f"{'' if m.confident else ' (not confident)'}"
    )


_NAMES = {"gain": "gain", "tau": "tau", "theta_ratio": "theta/tau"}


def _ranges(edges: dict[str, tuple[float, float]]) -> str:
    """Envelope edges (:func:`box.edges <service.engine.box.edges>`) as text, to 4 digits:
    the apparent values near them are told apart at the per mille (0.1663 vs 0.1667)."""
    g, t, th = edges["gain"], edges["tau"], edges["theta_ratio"][1]
    return f"gain {g[0]:.4g}..{g[1]:.4g}, tau {t[0]:.4g}..{t[1]:.4g}, theta/tau up to {th:.4g}"


def _placed(app: dict[str, float], leave: dict, back: dict) -> str:
    """Each apparent value (4 digits), and where it lies: beyond the envelope's edge (by
    how much), or inside it but beyond the edge a paused loop resumes within."""
    parts = []
    for key, name in _NAMES.items():
        x, (lo, hi), (b_lo, b_hi) = app[key], leave[key], back[key]
        if x < lo or x > hi:
            edge = lo if x < lo else hi
            where = f"{abs(x / edge - 1) * 100:.2g} % beyond the envelope's edge {edge:.4g}"
        elif x < b_lo or x > b_hi:
            where = f"inside the envelope, beyond the resume edge {b_lo if x < b_lo else b_hi:.4g}"
        else:
            where = ""
        parts.append(f"{name} {x:.4g}" + (f" ({where})" if where else ""))
    return ", ".join(parts)


def _manual(tb, s, wall) -> str:
    return (
        f"the gateway reports the loop in manual ({_g(100 * tb.w_manual[s])} % of the "
        "recent window): tuning pauses. Next: put the loop back in auto in the DCS"
    )


def _saturated(tb, s, wall) -> str:
    if tb.oh_held[s]:
        what = f"the data show the output held at {_g(tb.oh_op[s])}"
    elif tb.ps_held[s]:
        what = "the PV has not followed the output the PI law gives (no op in the samples)"
    else:
        what = "the gateway reports the output saturated"
    return (
        f"{what} ({_g(100 * tb.w_sat[s])} % of the recent window saturated): tuning "
        "pauses. Next: check the valve, its limits and the transmitter; tuning resumes "
        "once the output moves within its range"
    )


def _oscillating(tb, s, wall) -> str:
    return (
        f"the loop oscillates at its last-good gains (period {_g(tb.o_per[s])} s): tuning "
        f"pauses until t = {tb.osc_until[s]:.10g} (plant time), extended while it does. "
        "Next: look for a cause outside the gains (a sticking valve, an oscillating load "
        "or upstream loop, a changed plant); detune the loop if it persists"
    )


def _hint_mismatch(tb, s, wall) -> str:
    tol = tb.configs[tb.ids[s]].guard.hint_tolerance
    app = _apparent(tb, s)
    seen = "the model that flagged it is no longer the latest"
    seen = seen if app is None else _seen(tb.scaling_of(s), app)
    return (
        f"the identified model disagrees with the scaling in force (the hint, or a model "
        f"identified before) by more than guard.hint_tolerance ({_g(tol)}x): {seen}; tuning "
        "continues on that scaling. Next: PATCH "
        "guard.auto_rescale true (the next confident model rescales the loop), or register "
        "it again with the identified K and tau as k_hat and tau_hat"
    )


def _quiet(tb, s, wall) -> str:
    from service.engine import rules  # (rules imports the table, which imports this module)

    guard = tb.configs[tb.ids[s]].guard
    slots = np.array([s])
    has_sp = ~np.isnan(tb.sp_ref[slots])  # (a loop sending only e: a jump of e, two samples)
    step, noise = (float(x[0]) for x in rules.gate_step(tb, slots, has_sp))
    least = (
        f"guard.excitation_min_step ({_g(guard.excitation_min_step)} pv_scales = "
        f"{_g(float(tb.exc_step[s]))} in pv units)"
    )
    if noise > tb.exc_step[s]:  # the noise rule holds the gate
        least = (
            f"{_g(step)} (pv units): {_g(rules.EXCITATION_NOISE_SIGMAS)} x the measured "
            f"noise sigma{'' if has_sp[0] else ' of a jump of e'} "
            f"({_g(step / rules.EXCITATION_NOISE_SIGMAS)}), more than {least}"
        )
    return (
        f"no setpoint move of at least {least} in the last guard.excitation_periods "
        f"({_g(guard.excitation_periods)}) RL periods ({_g(tb.exc_window[s])} s): the agent "
        "waits for one (it learns from setpoint responses). Next: move the setpoint by "
        "that much, reduce the measurement noise, or PATCH guard.excitation_periods"
    )


_WHY = {
    LoopStatus.frozen: _frozen, LoopStatus.waiting: _waiting, LoopStatus.stale: _stale,
    LoopStatus.gains_out_of_bounds: _out_of_bounds, LoopStatus.identifying: _identifying,
    LoopStatus.out_of_envelope: _out_of_envelope, LoopStatus.manual: _manual,
    LoopStatus.saturated: _saturated, LoopStatus.oscillating: _oscillating,
    LoopStatus.hint_mismatch: _hint_mismatch, LoopStatus.quiet: _quiet,
}  # fmt: skip
"""The ``status_why`` of each status but ``tuning``."""
