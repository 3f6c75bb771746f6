"""The FOPTD fit's grid search (service.engine.foptd_fit) against its definition: at each
(tau, theta) the residual of the model response, as the recorder's rows see it, regressed
on (b, K, c)."""

from __future__ import annotations

import numpy as np
import pytest

from service.engine.foptd_fit import Window, _response, _sse_grid, recorded


def _sse_direct(w: Window, tau: float, theta: float) -> float:
    """One grid point the slow way: simulate the delayed lag, observe, solve, sum."""
    steps = np.arange(w.t.size)
    x = _response(w.t, w.v, tau, theta, w.dt)
    basis = np.stack([np.ones_like(x), x, np.exp(-w.dt * steps / tau)])
    basis = w.observe(basis, weighted=True).T
    coef, *_ = np.linalg.lstsq(basis, w.y, rcond=None)
    return float(((basis @ coef - w.y) ** 2).sum())


@pytest.mark.parametrize("rows", ["every sample", "recorder means"])
def test_the_grid_search_sums_of_squares_are_those_of_the_definition(rows):
    rng = np.random.default_rng(3)
    n = 300
    t = 0.5 * np.arange(n)
    op = 4.0 + np.cumsum(rng.normal(size=n))  # an offset: b and c absorb it
    pv = np.cumsum(rng.normal(size=n))
    if rows == "every sample":
        w = Window.of(t, pv, op)
    else:  # the recorder kept every other sample late in the window, and the last row 2
        keep = np.r_[0:100, 100:n:2]
        w = recorded(t[keep], pv[keep], op[keep], last=2)
        assert w.rows is not None and w.count.max() == 2
    taus = np.array([0.2, 3.0, 40.0, 900.0])
    thetas = np.array([0.0, 0.3, 1.25, 7.7, 60.0])  # whole and fractional samples
    direct = np.array([[_sse_direct(w, tau, th) for th in thetas] for tau in taus])
    np.testing.assert_allclose(_sse_grid([w], taus, thetas), direct, rtol=1e-9)
