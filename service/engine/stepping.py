"""One batched RL step of the due loops: the agent, then the safety guard.

Safety guard, per loop: new gains are clipped to the loop's absolute bounds, then to at
most a relative change ``r`` per update ([old / (1 + r), old * (1 + r)], symmetric in log
space), so a gain outside bounds a PATCH narrowed is walked back gradually (gains the
gateway reports outside them hold the loop instead: :func:`service.engine.reported.held`).
``auto`` loops take the guarded gains at once (an update in flight until the gateway
reports them); ``advisory`` loops are stepped and their proposals published, but their
gains change only when the gateway reports new ones; ``shadow`` loops are stepped and
their proposals recorded in the audit log with a predicted effect, never published.
Advisory and shadow proposals follow a proposal track (see :mod:`service.engine.track`):
the agent's step is added to the previous proposal, and the guard applies from it; the
track goes no farther than its reach from the gains in force (a step it holds there is
not published, ``guard=reach``).

With an identified model in force, a step the model predicts to track much worse than
the model's tuning is held (:mod:`service.engine.model_check`): gains unchanged, nothing
published, ``guard=model``.

Every step's gains message and audit row carry a short ``key=value`` reason
(:func:`_why`).
"""

from __future__ import annotations

import numpy as np

from service.engine import box, fences, margin, model_check, oscillation, predict, track, verify
from service.engine.audit import audit_row
from service.engine.modes import ADVISORY, AUTO, SHADOW
from service.engine.rules import GAIN_RTOL
from service.engine.table import LoopTable
from service.engine.updates import MODE_VALUES, StepResult, published
from service.wire.protocol import UpdateReason

OBS_LIMIT = 1e30
"""Largest magnitude of an observation the agent is given: it computes in float32
(largest 3.4e38), and gains or integrals beyond this are absurd in any unit."""


def step(tb: LoopTable, slots: np.ndarray, wall: float) -> StepResult:
    """One batched agent step of the loops in ``slots`` (each due, each once).

    A loop whose numbers go non-finite or absurd (a gain of 1e12 on a loop of extreme
    scaling, say) is left out of the batch, its state untouched, and recorded as a
    ``fault``; the other loops are stepped as if it were not there.
    """
    obs = _observe(tb, slots)
    sane = (np.abs(obs) <= OBS_LIMIT).all(axis=1)  # False for NaN too
    if not sane.all():
        _faults(tb, slots[~sane], wall, "observation non-finite or beyond 1e30")
        slots, obs = slots[sane], obs[sane]
    if tb._policy is not None:
        state = tb.hidden[slots]  # a contiguous copy, updated in place
        delta = tb._policy.step_inplace(obs, state, tb.forgetting[slots])
    else:
        delta, state = tb.agent.act(obs, tb.hidden[slots], tb.forgetting[slots])
    kp_unit, ki_unit = tb.kp_unit[slots], tb.ki_unit[slots]
    proposed = np.column_stack(
        [(obs[:, 0] + delta[:, 0]) * kp_unit, (obs[:, 1] + delta[:, 1]) * ki_unit]
    )
    damped = tb.damp[slots] > 0
    if damped.any():
        proposed = _damp(tb, slots, obs, proposed, damped)
    sane = np.isfinite(proposed).all(axis=1) & np.isfinite(state).all(axis=(1, 2))
    if not sane.all():
        _faults(tb, slots[~sane], wall, "non-finite agent output")
        slots, proposed, state = slots[sane], proposed[sane], state[sane]
    settling = tb.settle[slots] > 0
    if settling.any():
        proposed = _settle(tb, slots, proposed, settling)
    tb.hidden[slots] = state
    old = np.column_stack([tb.kp[slots], tb.ki[slots]])
    mode = tb.mode[slots]
    # advisory and shadow proposals: the agent's step added to the previous proposal
    walked = (mode == ADVISORY) | (mode == SHADOW)
    base = old
    if walked.any():
        prev = np.column_stack([tb.adv_kp[slots], tb.adv_ki[slots]])
        base = np.where(walked[:, None] & np.isfinite(prev), prev, old)
        proposed = proposed + (base - old)
    grow = 1.0 + tb.max_rel[slots, None]
    lo = np.column_stack([tb.kp_min[slots], tb.ki_min[slots]])
    hi = np.column_stack([tb.kp_max[slots], tb.ki_max[slots]])
    # a rollback's fence first (fmin/fmax pass NaN, no fence), the loop's bounds over it
    fence_lo, fence_hi = fences.fence(tb, slots, tb.last_t[slots])
    fenced = np.fmin(np.fmax(proposed, fence_lo), fence_hi)
    bounded = np.clip(fenced, lo, hi)
    new = np.clip(bounded, base / grow, base * grow)
    cut = tb.watch[slots] & (tb.ms_max[slots] > 0)
    if cut.any():
        new, cut = _margin(tb, slots, new, cut, lo)
    # the track waits at its reach of the gains in force for a decision (track.REACH_STEPS)
    far = np.zeros(len(slots), bool)
    if walked.any():
        new, far = track.within_reach(tb, slots, walked, old, base, new)
    # the model check: a step the identified model predicts much worse is held (no change,
    # nothing published; the agent's state moves on)
    hold, held_text = model_check.held(tb, slots, base, new)
    # a step from gains outside the bounds (narrowed by a PATCH, or an operator's) into
    # them is the guard's, not the agent's: held, the gains stayed outside for good
    hold &= ~((base < lo) | (base > hi)).any(axis=1)
    if hold.any():
        new = np.where(hold[:, None], base, new)
        tb.n_model_holds[slots[hold]] += 1
    # the view's hold (views.hold): since when the model check has held the loop's steps
    tb.mc_since[slots] = np.where(hold, np.fmin(tb.mc_since[slots], tb.last_t[slots]), np.nan)
    go = ~hold & ~far

    applied = (mode == AUTO) & go
    auto = slots[applied]
    tb.prev_kp[auto], tb.prev_ki[auto] = old[applied, 0], old[applied, 1]
    tb.kp[auto], tb.ki[auto] = new[applied, 0], new[applied, 1]
    tb.pending[auto], tb.auto_seq[auto] = True, tb.seq[auto] + 1
    moved = slots[go]
    tb.seq[moved] += 1
    tb.n_steps[slots] += 1
    tb._gains_dirty.update(moved.tolist())
    walked &= go
    if walked.any():
        tracked = slots[walked]
        kp, ki = new[walked].T
        track.propose(tb, tracked, kp, ki, tb.seq[tracked], UpdateReason.agent)
        tb._verify_dirty.update(tracked.tolist())

    ids, gateways, listed = tb.ids, tb.gateways, slots.tolist()
    result = StepResult(
        [ids[s] for s in listed],
        tb.last_t[slots],
        tb.seq[slots],
        mode,
        old,
        proposed,
        new,
        [gateways[s] for s in listed],
        why=_why(tb, slots, mode, old, proposed, fenced, bounded, new, cut, hold, far),
    )
    limited = np.flatnonzero(~np.isclose(proposed, new, rtol=GAIN_RTOL, atol=0.0).all(axis=1))
    # the audit row adds the figures the change was made on: the last response's IAE and
    # the last-good gains' (its verdict row will add the figure after); it drops
    # "verdict=pending", which a stored row would claim after its verdict came
    details = [
        f"{why.removesuffix(PENDING)} iae={f:.4g} good_iae={g:.4g}"
        for why, f, g in zip(result.why, tb.f_iae[slots].tolist(),
                             verify.reference(tb, slots).tolist(),
                             strict=True)
    ]  # fmt: skip
    # formatting Python floats, not numpy scalars: a cold loop is limited in most steps
    for i, (kp, ki) in zip(limited.tolist(), proposed[limited].tolist(), strict=True):
        details[i] = f"{details[i]}; {_guard_detail(kp, ki)}"
    for i in np.flatnonzero(hold).tolist():
        details[i] = f"{details[i]}; {held_text[i]}"
    for i in np.flatnonzero(far).tolist():
        details[i] = f"{details[i]}; {WAITS}"
    shadow = np.flatnonzero(mode == SHADOW)
    if shadow.size:
        predicted = predict.predictions(tb, slots[shadow].tolist(), old[shadow], new[shadow])
        for i, text in zip(shadow.tolist(), predicted, strict=True):
            details[i] = f"{details[i]} {text}"
    mode_names = [MODE_VALUES[c] for c in mode.tolist()]
    tb._audit.extend(
        zip(
            result.loop_ids, [wall] * len(slots), result.t.tolist(), result.seq.tolist(),
            mode_names, ["agent"] * len(slots), old[:, 0].tolist(), old[:, 1].tolist(),
            new[:, 0].tolist(), new[:, 1].tolist(), details, strict=True,
        )
    )  # fmt: skip
    unpublished = np.flatnonzero((mode == SHADOW) | hold | far)
    if unpublished.size:
        result, slots = result.without(unpublished), np.delete(slots, unpublished)
    return published(tb, slots, result)


def _why(tb, slots, mode, old, proposed, fenced, bounded, new, cut, hold, far) -> list[str]:
    """The short ``key=value`` reason of each step (docs/tuner.md, Reasons): the loop's
    basis (an identified model or the hint), the change, which guard limit bit, and the
    verdict to come."""
    with np.errstate(divide="ignore", invalid="ignore"):
        pct = (new / old - 1.0) * 100.0

    def differ(a, b):
        return ~np.isclose(a, b, rtol=GAIN_RTOL, atol=0.0).all(axis=1)

    # the limit named: the model's hold, else the proposal's reach, else the margin's cut,
    # else the first of the fence, the bounds and the rate (the order they apply in) that
    # changed the gains
    guards = np.select(
        [hold, far, cut, differ(proposed, fenced), differ(fenced, bounded), differ(bounded, new)],
        ["model", "reach", "margin", "fence", "bounds", "rate"],
        "none",
    ).tolist()
    basis = ["model" if tb.ident[s].scaling is not None else "hint" for s in slots.tolist()]
    made = [_VERDICT.get(c, NO_VERDICT) for c in mode.tolist()]
    verdicts = np.where(hold | far, NO_VERDICT, made)
    return [
        f"reason=agent basis={b} dkp={p[0]:+.1f}% dki={p[1]:+.1f}% guard={g} verdict={v}"
        for b, p, g, v in zip(basis, pct.tolist(), guards, verdicts.tolist(), strict=True)
    ]


_VERDICT = {AUTO: "pending", ADVISORY: "proposal", SHADOW: "shadow"}
NO_VERDICT = "none"
"""The verdict of a step none will judge: one the model check held changed nothing."""
WAITS = "the proposal waits at its reach of the gains in force for a decision (accept or reject)"
"""The audit detail of a step the proposal's reach held (:func:`track.within_reach`)."""
PENDING = f" verdict={_VERDICT[AUTO]}"
"""The end of an ``auto`` step's reason (:func:`_why`): its verdict is to come, in a
verdict row of its own (the history's ``verdict``, :mod:`service.daemon.verdicts`)."""


def _observe(tb: LoopTable, slots: np.ndarray) -> np.ndarray:
    """The agent's observation [kp, ki, e, int_e] in its units, (n, 4): e the mean error
    over the end of the RL period (:func:`service.units.error_window`); e and int_e scaled
    by the loop's setpoint-move gain (:data:`service.units.PAPER_MOVE`)."""
    with np.errstate(over="ignore", invalid="ignore"):  # absurd loops are caught after
        return np.column_stack(
            [
                tb.kp[slots] / tb.kp_unit[slots],
                tb.ki[slots] / tb.ki_unit[slots],
                tb.obs_e[slots] * tb.obs_gain[slots],
                tb.int_e[slots] * tb.obs_gain[slots],
            ]
        )


def _margin(tb: LoopTable, slots, new, check, lo) -> tuple[np.ndarray, np.ndarray]:
    """The robustness guard: where the loop's identified model (the latest confident one,
    else the one in force), seen through the scaling in force, lies outside the agent's
    training box (:func:`service.engine.box.in_box`: where the agent extrapolates; inside
    it the best gains reach Ms 1.35 and the check would only cost time), gains whose
    largest sensitivity on the model is above ``guard.max_sensitivity`` (or unstable) are
    scaled down together to it, never below the loop's lower bounds ``lo`` (n, 2): the
    bounds are the user's word (a gain the rate clip left below its bound, walking back
    into the bounds, is not cut further). Returns the gains and where the guard cut
    them."""
    rows, models = [], []
    for i in np.flatnonzero(check).tolist():
        s = int(slots[i])
        st = tb.ident[s]
        m = st.model if st.model is not None and st.model.confident else st.in_force
        if m is not None and not m.integrating and not box.in_box(tb.scaling_of(s), m):
            rows.append(i)
            models.append((m.k, m.tau, m.theta))
    cut = np.zeros(len(slots), bool)
    if not rows:
        return new, cut
    K, tau, theta = np.array(models).T
    scale = margin.robust_factor(new[rows, 0], new[rows, 1], K, tau, theta, tb.ms_max[slots[rows]])
    new = new.copy()
    new[rows] = np.maximum(new[rows] * scale[:, None], np.minimum(new[rows], lo[rows]))
    cut[rows] = scale < 1.0
    return new, cut


NOISE_FLOOR = 0.01
"""Noise sigma (agent units, 1 % of pv_scale) below which a loop counts as noise-free for
the noise damping: the monitor's second-difference estimate on a smooth noise-free
response stays well under it."""


def _damp(tb: LoopTable, slots, obs, proposed, damped) -> np.ndarray:
    """The agent's change of the gains scaled by e^2 / (e^2 + (d sigma)^2): a step read
    from an error the size of the noise moves the gains little (docs/tuner.md, Noise
    damping). ``obs[:, 2]`` is the error as the agent read it (agent units, times the
    setpoint-move gain), sigma the monitor's noise estimate in the same units."""
    sigma = oscillation.noise_sigma(tb, slots) * tb.e_scale[slots]
    sigma = np.where(sigma > NOISE_FLOOR, sigma * tb.obs_gain[slots], 0.0)
    noise = (tb.damp[slots] * sigma) ** 2
    e2 = obs[:, 2] ** 2
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(damped & (noise > 0), e2 / (e2 + noise), 1.0)
    old = np.column_stack([tb.kp[slots], tb.ki[slots]])
    return old + w[:, None] * (proposed - old)


SETTLE_FLOOR = 0.1
"""Smallest share of the agent's step a settled loop takes (``guard.settle_steps``)."""
SETTLE_MEMORY = 0.9
"""Decay per step of the running sum of the log changes the agent asks for."""
SETTLE_RESET = 1.2
"""That sum (log units: 3.3x) beyond which the agent is asking for a real change (a plant
that moved): full steps again. Its steps on a noisy loop, settled, sum to less (measured:
docs/tuner.md, Robustness measures 7)."""


def _settle(tb: LoopTable, slots, proposed, settling) -> np.ndarray:
    """Settling: the agent's change of the gains (log units) scaled by settle_steps / n,
    n its steps in the episode, between SETTLE_FLOOR and 1, so that converged gains stop
    wandering with the noise and the load; n starts again where the agent keeps asking for
    a large change (docs/tuner.md, Robustness measures 7)."""
    old = np.column_stack([tb.kp[slots], tb.ki[slots]])
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ask = np.log(proposed / old)
    usable = settling & np.isfinite(ask).all(axis=1)
    ask = np.where(usable[:, None], ask, 0.0)
    s = slots[usable]
    acc = SETTLE_MEMORY * np.column_stack([tb.settle_kp[s], tb.settle_ki[s]]) + ask[usable]
    change = (np.abs(acc) > SETTLE_RESET).any(axis=1)
    n = np.where(change, 1.0, tb.settle_n[s] + 1.0)
    tb.settle_n[s] = n
    tb.settle_kp[s], tb.settle_ki[s] = np.where(change[:, None], 0.0, acc).T
    share = np.ones(slots.size)
    share[usable] = np.clip(tb.settle[s] / n, SETTLE_FLOOR, 1.0)
    with np.errstate(over="ignore", invalid="ignore"):
        return np.where(usable[:, None], old * np.exp(share[:, None] * ask), proposed)


def _faults(tb: LoopTable, slots: np.ndarray, wall: float, why: str) -> None:
    tb.n_faults[slots] += 1
    for s in slots.tolist():
        gains = (float(tb.kp[s]), float(tb.ki[s]))
        tb._audit.append(
            audit_row(
                tb.ids[s], wall, float(tb.last_t[s]), int(tb.seq[s]), tb.mode_of(s).value,
                "fault", gains, gains, f"not stepped: {why}",
            )
        )  # fmt: skip


def _guard_detail(kp: float, ki: float) -> str:
    return f"limited by the safety guard (proposed kp={kp:.6g}, ki={ki:.6g})"
