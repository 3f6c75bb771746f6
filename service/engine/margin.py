"""Robustness of a PI loop on a first-order-plus-dead-time model, vectorised: the gain
margin and the largest sensitivity, and the largest common factor on the gains that keeps
the sensitivity within a bound (the robustness guard, docs/tuner.md).

L(s) = (kp + ki/s) K exp(-theta s) / (tau s + 1). Its phase -pi/2 + atan(kp w / ki) -
atan(tau w) - theta w reaches -pi first at some w180 <= pi/theta (the PI's and the lag's
terms together stay within (-pi, 0)), where the gain margin is 1 / |L(j w180)|. Scaling
both gains by c scales L by c: the margin by 1/c exactly, the sensitivity
Ms = max_w 1 / |1 + L(jw)| monotonically in practice (1 at c = 0), so a bisection on c
finds the largest factor within the bound, whatever the ratio kp/ki. Ms is meaningful
for a stable loop only: Ms <= m implies a gain margin of at least m / (m - 1), which is
required first.
"""

from __future__ import annotations

import numpy as np

GRID = np.geomspace(1e-3, np.pi, 256)
"""w theta at which the phase is evaluated (the first crossing of -pi lies below pi)."""
WGRID = np.geomspace(1e-2, 1e2, 128)
"""w (tau + theta) at which the sensitivity is evaluated."""
PEAK = np.geomspace(0.8, 1.25, 33)
"""w over the gain crossover at which the sensitivity is also evaluated."""
BISECTIONS = 12
"""Halvings of the factor's interval (a precision of 2.4e-4 of the gains)."""


def gain_margin(kp, ki, K, tau, theta) -> np.ndarray:
    """Gain margin of PI (kp, ki per second) on K exp(-theta s) / (tau s + 1) (seconds),
    arrays (n,); inf where theta is 0 (a PI on a first-order lag never reaches -pi)."""
    kp, ki, K, tau, theta = _arrays(kp, ki, K, tau, theta)
    out = np.full(kp.shape, np.inf)
    live = theta > 0
    if not live.any():
        return out
    th = theta[live, None]
    w = GRID[None, :] / th
    phase = (
        -np.pi / 2 + np.arctan2(kp[live, None] * w, ki[live, None])
        - np.arctan(tau[live, None] * w) - GRID[None, :]
    )  # fmt: skip
    i = np.argmax(phase <= -np.pi, axis=1)  # first crossing (the last point always is)
    rows = np.arange(i.size)
    p0, p1 = phase[rows, i - 1], phase[rows, i]
    frac = np.clip((p0 + np.pi) / np.maximum(p0 - p1, 1e-12), 0.0, 1.0)
    w180 = w[rows, i - 1] + frac * (w[rows, i] - w[rows, i - 1])
    mag = K[live] * np.hypot(kp[live], ki[live] / w180) / np.hypot(1.0, tau[live] * w180)
    with np.errstate(divide="ignore"):
        out[live] = 1.0 / mag
    return out


def sensitivity(kp, ki, K, tau, theta) -> np.ndarray:
    """Largest sensitivity max_w 1 / |1 + L(jw)| (n,); meaningful for stable loops only.
    Evaluated on :data:`WGRID` and around the gain crossover (:func:`_crossover`), where
    a lightly damped loop's narrow peak lies: the grid alone read 0.11 for 313 (kp 0.01,
    ki 1e5 on K 1, tau 1 s, no dead time: its peak at 316 rad/s, beyond the grid's top)
    and 6.27 for 6.82 (kp 0.05, ki 50: between two of its points)."""
    kp, ki, K, tau, theta = _arrays(kp, ki, K, tau, theta)
    w = np.concatenate(
        [
            WGRID[None, :] / (tau + theta)[:, None],
            _crossover(kp, ki, K, tau, theta)[:, None] * PEAK,
        ],
        axis=1,
    )
    s = 1j * w
    loop = (
        (kp[:, None] + ki[:, None] / s) * K[:, None] * np.exp(-theta[:, None] * s)
        / (tau[:, None] * s + 1.0)
    )  # fmt: skip
    return (1.0 / np.abs(1.0 + loop)).max(axis=1)


def _crossover(kp, ki, K, tau, theta) -> np.ndarray:
    """The frequency at which |L(jw)| = 1 (n,) (the dead time leaves the magnitude alone):
    the positive root w^2 of tau^2 w^4 + b w^2 - K^2 ki^2 = 0, b = 1 - K^2 kp^2 (in the
    form without cancellation for either sign of b); where |L| stays below 1 (ki 0 and
    K kp below 1), :data:`WGRID`'s lowest frequency, which is evaluated anyway."""
    b = 1.0 - (K * kp) ** 2
    root = np.sqrt(b * b + 4.0 * (tau * K * ki) ** 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        w2 = np.where(b > 0.0, 2.0 * (K * ki) ** 2 / (root + b), (root - b) / (2.0 * tau * tau))
    return np.where(w2 > 0.0, np.sqrt(np.maximum(w2, 0.0)), WGRID[0] / (tau + theta))


def robust_factor(kp, ki, K, tau, theta, ms_max) -> np.ndarray:
    """The largest c in [0, 1] with gain margin >= ms_max / (ms_max - 1) and sensitivity
    <= ms_max for the gains (c kp, c ki) (n,); 1 where the gains already are."""
    kp, ki, K, tau, theta, ms_max = _arrays(kp, ki, K, tau, theta, ms_max)
    cap = np.minimum(1.0, gain_margin(kp, ki, K, tau, theta) * (ms_max - 1.0) / ms_max)
    ok = sensitivity(cap * kp, cap * ki, K, tau, theta) <= ms_max
    lo, hi = np.where(ok, cap, 0.0), cap
    for _ in range(BISECTIONS):
        if ok.all():
            break
        mid = 0.5 * (lo + hi)
        good = sensitivity(mid * kp, mid * ki, K, tau, theta) <= ms_max
        lo, hi = np.where(ok | ~good, lo, mid), np.where(ok | good, hi, mid)
    return lo


def _arrays(*values) -> list[np.ndarray]:
    return [np.atleast_1d(v) for v in np.broadcast_arrays(*(np.asarray(v, float) for v in values))]
