"""The gain margin of a PI loop on a first-order-plus-dead-time model, vectorised.

The dead-time guard (docs/tuner.md, Dead-time guard) keeps every agent step's gains at a
gain margin of at least ``guard.min_gain_margin`` on the loop's identified model: the
agent was trained on theta/tau up to 1 (2 with the v3 mix) and on a dead-time dominant
plant it pushes the integral gain past stability.

L(s) = (kp + ki/s) K exp(-theta s) / (tau s + 1); its phase
-pi/2 + atan(kp w / ki) - atan(tau w) - theta w reaches -pi first at some w180 <= pi/theta
(the PI's and the lag's terms together stay within (-pi, 0)), where the margin is
1 / |L(j w180)|. Scaling both gains by c scales L by c, so c = GM / GM_min brings a loop
to the margin exactly, whatever the ratio kp/ki.
"""

from __future__ import annotations

import numpy as np

GRID = np.geomspace(1e-3, np.pi, 256)
"""w theta at which the phase is evaluated (the first crossing of -pi lies below pi)."""


def gain_margin(kp, ki, K, tau, theta) -> np.ndarray:
    """Gain margin of PI (kp, ki per second) on K exp(-theta s) / (tau s + 1) (seconds),
    arrays (n,); inf where theta is 0 (a PI on a first-order lag never reaches -pi)."""
    kp, ki, K, tau, theta = np.broadcast_arrays(
        *(np.asarray(v, dtype=np.float64) for v in (kp, ki, K, tau, theta))
    )
    out = np.full(kp.shape, np.inf)
    live = theta > 0
    if not live.any():
        return out
    th = theta[live, None]
    w = GRID[None, :] / th
    with np.errstate(divide="ignore"):
        phase = (
            -np.pi / 2 + np.arctan2(kp[live, None] * w, ki[live, None])
            - np.arctan(tau[live, None] * w) - GRID[None, :]
        )  # fmt: skip
    i = np.argmax(phase <= -np.pi, axis=1)  # first crossing (the last point always is)
    rows = np.arange(i.size)
    p0, p1 = phase[rows, i - 1], phase[rows, i]
    frac = np.clip((p0 + np.pi) / np.maximum(p0 - p1, 1e-12), 0.0, 1.0)
    w180 = w[rows, i - 1] + frac * (w[rows, i] - w[rows, i - 1])
    mag = (
        K[live]
        * np.hypot(kp[live], ki[live] / w180)
        / np.hypot(1.0, tau[live] * w180)
    )  # fmt: skip
    with np.errstate(divide="ignore"):
        out[live] = 1.0 / mag
    return out
