"""The sample-by-sample part of one RL period of the training environment: the closed
loops in C (``service/learn/_period.c``) and the setpoint-move rule where it can fire.

:meth:`service.learn.env.TuningEnv.step` runs 275 controller samples an RL period; one
numpy call per sample and operation made the interpreter, not the arithmetic, two thirds
of an imitation epoch. The kernel does the same arithmetic on the same doubles in the
same order (no fused multiply-add), so both paths give the same numbers bit for bit
(tested); the numpy loop in ``TuningEnv.step`` stays the definition and the fallback
where the optional extension is not built."""

from __future__ import annotations

import numpy as np

from service.units import MOVE_STEP, error_window, track_moves

try:
    from service.learn import _period
except ImportError:  # installed without a C compiler: TuningEnv runs its numpy loop
    _period = None
KERNEL = _period is not None
"""Whether the C sample loop is built (tests switch it off to compare the two paths)."""


def run(env, sp, sq, load, noise, walk) -> tuple[np.ndarray, np.ndarray]:
    """One RL period of ``env`` (a :class:`~service.learn.env.TuningEnv`, from inside
    ``step``): the (B, inner) setpoints ``sp``, loads ``load``, noise ``(a_n, w_n)`` and
    load walk ``(a_w, w_w)`` as ``step`` drew them (None: none); squared tracking
    errors are summed into ``sq``; the plant, PI, target, noise and load states, the
    error integral, the setpoint and the sample counter advance. Returns the sums of the
    agent's error window (``total``, ``count``: :func:`service.units.error_window`)."""
    plant, target, pi, n, inner = env.plant, env.target, env.pi, env.n, env.inner
    a_n, w_n = noise if noise is not None else (None, None)
    a_w, w_w = walk if walk is not None else (0.0, None)
    e = np.empty((n, inner))

    held = []  # the inputs' contiguous copies live until the call returns

    def at(a, dtype=np.float64):
        if a.dtype != dtype or not a.flags.c_contiguous or not a.flags.writeable:
            raise ValueError("the period kernel needs contiguous, writable state arrays")
        return a.ctypes.data

    def src(a, dtype=np.float64):
        if a is None:
            return 0
        held.append(np.ascontiguousarray(a, dtype))
        return held[-1].ctypes.data

    lag2 = (plant.tau2 > 0).astype(np.uint8) if plant.lag2 else None
    _period.run(
        n, inner, plant._ptr, target._ptr,
        at(plant.x), at(plant.x1), at(plant._buf), src(plant.a), src(plant.b),
        src(plant.a2), src(plant.delay, np.int64), src(lag2, np.uint8),
        plant._buf.shape[1],
        at(target.x), at(target._buf), src(target.a), src(target.b),
        src(target.delay, np.int64), target._buf.shape[1],
        src(pi.kp), src(pi.ki), src(pi.bias), at(pi.integral), at(pi.e_last),
        at(pi.saturated, np.bool_), env.cfg.dt, pi.u_min, pi.u_max, env.cfg.err_cap,
        src(sp), at(e), at(sq), at(env.int_e),
        at(env.noise_state) if a_n is not None else 0, src(a_n), src(w_n),
        src(load), at(env.load_walk) if load is not None else 0, src(w_w), a_w,
    )  # fmt: skip
    plant._ptr = (plant._ptr + inner) % plant._buf.shape[1]
    target._ptr = (target._ptr + inner) % target._buf.shape[1]
    # the window rule on every sample at once, summed in sample order (as the loop sums)
    due = env.k + inner
    terms = error_window(e, env.k + np.arange(inner), due, inner, 0.0, 0.0, due)
    env.sp, env.k = sp[:, -1], due
    return tuple(np.cumsum(np.broadcast_to(x, e.shape), axis=1)[:, -1] for x in terms)


def track_moves_over(env, sp: np.ndarray) -> None:
    """The engine's setpoint-move rule (:func:`service.units.track_moves`) over the
    (B, inner) setpoints ``sp`` of ``env``'s coming RL period, with the engine's default
    smallest move and one RL period as the run window. The rule changes nothing at a
    sample where the setpoint lies less than a move (``MOVE_STEP``) from its reference
    (a NaN one always counts), so it runs only on the episodes and at the samples where
    it can fire: a few calls a period instead of one per sample of a ramp."""
    names = ("sp_ref", "sp_anchor", "move_k", "obs_gain")
    rows = np.flatnonzero((~(np.abs(sp - env.sp_ref[:, None]) < MOVE_STEP)).any(axis=1))
    if rows.size == 0:
        return
    sp, state, j = sp[rows], [getattr(env, a)[rows] for a in names], 0
    while j < env.inner:
        far = ~(np.abs(sp[:, j:] - state[0][:, None]) < MOVE_STEP)
        cols = np.flatnonzero(far.any(axis=0))
        if cols.size == 0:
            break
        j += int(cols[0])
        state = track_moves(sp[:, j], *state, now=env.k + j, step=MOVE_STEP,
                            run=env.inner)[1:5]  # fmt: skip
        j += 1
    for a, value in zip(names, state, strict=True):
        whole = getattr(env, a).copy()
        whole[rows] = value
        setattr(env, a, whole)
