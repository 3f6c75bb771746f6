"""What identification does with a model (:mod:`service.engine.watch` assesses the
segments): a confident model becomes a hint-free loop's scaling or checks the one in
force (mismatch flag, auto-rescale, the envelope guard, following a drifting plant);
an unconfident one may still pause the loop (:func:`envelope`). See
docs/identification.md, The envelope guard."""

from __future__ import annotations

import json
import math

from service.engine import box, first_tuning, identify, model_check, monitor
from service.engine.audit import audit_row
from service.engine.id_state import IdState
from service.units import AGENT_GAIN, AGENT_TAU, Scaling

NOISE_SCALE = 10.0
"""A hint-free loop's pv_scale is the typical setpoint move, at least this many times
the measurement noise (the agent sees errors of order 1 and noise well below)."""

INTEGRATING_K_RSE = 20.0
"""Largest relative standard error of the FOPTD's K with which an integrating verdict
pauses: on true integrators 0.26-0.62, up to 8 on a weakly excited one under noise (K
and tau collinear at tau's bound); on the integrating verdicts load steps at the plant
input gave 35-83 (the robustness suite's load-steps condition, session 30: without this
test one loop paused on such a verdict, its worst step-test MSE 0.027 -> 0.055)."""


def model_scaling(m: identify.Model, pv_scale: float | None = None) -> Scaling:
    """The section 5.4 scaling of a model: it appears with gain 0.5 and tau 0.5."""
    if pv_scale is None:
        pv_scale = max(m.move, NOISE_SCALE * m.noise)
    e_scale = 1.0 / pv_scale
    return Scaling(
        e_scale=e_scale, u_scale=e_scale * m.k / AGENT_GAIN, time_unit_s=m.tau / AGENT_TAU
    )


def use(tb, s: int, m: identify.Model, t: float, wall: float) -> None:
    """A confident model: the first scaling of a hint-free loop, or a check of the one in
    force (mismatch flag, auto-rescale, envelope guard)."""
    config = tb.configs[tb.ids[s]]
    guard = config.guard
    detail = json.dumps({k: v for k, v in m.as_dict().items()}, separators=(",", ":"))
    if not tb.scaled[s]:
        _put_in_force(tb, s, m, model_scaling(m), t, wall, "identified", detail)
        return
    scaling = tb.scaling_of(s)
    if hint_off(box.apparent(scaling, m), m.lumped) > math.log(guard.hint_tolerance):
        if not tb.mismatch[s]:  # flagged (and, with auto-rescale, rescaled right after)
            tb.n_mismatch[s] += 1
            audit(tb, s, t, wall, "mismatch", detail)
        tb.mismatch[s] = True
        if tb.site.rescales(guard):
            pv_scale = 1.0 / scaling.e_scale
            _put_in_force(tb, s, m, model_scaling(m, pv_scale), t, wall, "rescaled", detail)
            tb.mismatch[s] = False
    else:
        tb.mismatch[s] = False
    envelope(tb, s, m, t, wall, sure=True)
    if not tb.out_env[s]:  # the gains follow a plant drifting inside the envelope
        model_check.follow(tb, s, m, t, wall)  # (with a model in force)
        model_check.hint_checked(tb, s, m, wall)  # (without: a hinted loop)


def hint_off(app: dict[str, float], lumped: bool) -> float:
    """How far (log) the hint in force is off a confident model seen through it
    (:func:`box.apparent <service.engine.box.apparent>`), the worse of K and tau. A
    lumped model bounds tau only from above, by its lag tau + theta (the dead time may
    take any share of it): its tau counts only when the hint's is slower than the whole
    lag."""
    tau = math.log(app["tau"] / AGENT_TAU)
    if lumped:
        tau = min(0.0, tau + math.log1p(app["theta_ratio"]))
    return max(abs(math.log(app["gain"] / AGENT_GAIN)), abs(tau))


def envelope(tb, s: int, m: identify.Model, t: float, wall: float, *, sure: bool) -> None:
    """The envelope guard. A confident model (``sure``) decides both ways; one that passes
    every check but precision, or but consistency, only pauses, and only when even K and
    tau two standard errors toward the box leave it (a drifting plant is never pinned
    down, nor consistent, on data that mix its old and new dynamics: with the consistency
    test on an event that has shown its response, the bar's ramp was paused at 4.5 tau0
    instead of 4.0 until such models could pause). An integrating one (never confident)
    pauses when it fits, comes from enough events, passes :func:`integrating_pause` and
    its FOPTD's lag is out of the envelope too: the agent does not tune an integrator
    (docs/identification.md, Integrating processes), but a slow lag the scaling shows
    in the box is one it tunes (a segment shorter than the lag fits an integrator as
    well). One that fails any other check, or both (under load steps: misses of 8-30x
    the noise, pauses for good; docs/tuner.md, Session 17), is not used."""
    if not tb.env_guard[s]:
        return
    app = box.apparent(tb.scaling_of(s), m)
    if sure:  # a paused loop resumes only well inside (hysteresis: box.RESUME_MARGIN)
        margin = box.RESUME_MARGIN if tb.out_env[s] else box.ENVELOPE_MARGIN
        out = m.integrating or not box.in_envelope(app, margin)
    else:
        if not (m.r2 >= identify.MIN_R2 and m.events >= identify.MIN_EVENTS):
            return
        if m.integrating:
            out = integrating_pause(m) and not box.in_envelope(app)
        elif m.k > 0 and (identify.precise(m) or m.prediction <= identify.MAX_PREDICTION):
            out = not box.in_envelope(box.toward_box(app, 2.0 * m.k_rse, 2.0 * m.tau_rse))
        else:
            return
        if not out:
            return
    seen = box.as_seen(tb.scaling_of(s), m)
    detail = json.dumps(seen, separators=(",", ":"))
    if out and not tb.out_env[s]:
        tb.n_envelope[s] += 1
        audit(tb, s, t, wall, "out_of_envelope", detail)
        # what the loop's why names while paused (later models may differ): ~4 floats
        tb.ident[s].paused_by = {"t": float(t), **seen}
    elif not out and tb.out_env[s]:
        audit(tb, s, t, wall, "in_envelope", detail)
        tb.ident[s].paused_by = None
    tb.out_env[s] = out
    if out and sure:  # paused on the model's tuning (a no-op once the gains are at it)
        first_tuning.apply(tb, s, m, wall, "out_of_envelope")


def integrating_pause(m: identify.Model) -> bool:
    """Whether an integrating verdict is one to pause on: the integrator's K has the
    registered action's sign and the FOPTD's K is not lost in its standard error
    (:data:`INTEGRATING_K_RSE`)."""
    return m.slope > 0 and m.k_rse <= INTEGRATING_K_RSE


def _put_in_force(tb, s, m, scaling: Scaling, t, wall, reason: str, detail: str) -> None:
    st: IdState = tb.ident[s]
    st.scaling, st.in_force, st.in_force_t = scaling, m, t
    tb.reconfigure(tb.configs[tb.ids[s]])
    new_scaling(tb, s, t)
    if tb.exc_window[s] < math.inf:
        tb.excited_until[s] = t + tb.exc_window[s]
    tb.out_env[s], st.paused_by = False, None
    tb.n_identified[s] += 1
    audit(tb, s, t, wall, reason, detail)
    first_tuning.apply(tb, s, m, wall, reason)


def new_scaling(tb, s: int, t: float) -> None:
    """The scaling in force changed (or went: identifying again) at plant time ``t``: what
    was measured in the old one's units and RL period starts again. A fresh episode from
    the gains in force (the hidden state and the error integral are in the old agent
    units), a decimation window from ``t`` (NaN without a scaling: never due), and no open
    setpoint response: it was to be judged over two of the old RL periods, and without a
    scaling no move ends it (the excitation gate sees none), so it ran on past the next
    move and counted that move's error as overshoot (a false rollback). The moves that
    judged nothing are forgotten too: counted against the old RL period, the verification's
    why gave them under the new one's (12 cut short "after 200 s of the nan s")."""
    tb.hidden[s] = 0.0
    tb.unsettle(s)
    tb.int_e[s] = 0.0
    tb.next_due[s] = t + tb.period[s]
    tb.r_t0[s] = math.nan
    monitor.forget_unjudged(tb, s)


def audit(tb, s: int, t: float, wall: float, reason: str, detail: str) -> None:
    gains = (float(tb.kp[s]), float(tb.ki[s]))
    tb._audit.append(
        audit_row(tb.ids[s], wall, t, int(tb.seq[s]), tb.mode_of(s).value, reason, gains,
                  gains, detail)
    )  # fmt: skip
