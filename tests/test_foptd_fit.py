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


def test_standard_errors_grow_with_slow_residuals_and_not_with_white_ones(monkeypatch):
    """service.engine.foptd_fit._covariance: on white measurement noise tau's standard
    error is the scatter of its estimates; with a slow disturbance on the measurement
    (a random walk the linear model cannot explain) the estimates scatter 25x more and
    the Newey-West sandwich's error grows 2.6x beyond the textbook form's (still about a
    third of the scatter: a random walk outlasts any lag window)."""
    from plant_sim.foptd import FOPTDBatch
    from service.engine import foptd_fit

    def fits(slow: float) -> tuple[float, float]:
        """(scatter of log tau, median standard error) over 12 noise draws."""
        taus, ses = [], []
        for seed in range(12):
            rng = np.random.default_rng(seed)
            n = 600
            op = np.repeat(rng.choice([-1.0, 1.0], n // 60), 60) * 10.0  # steps every 60
            plant = FOPTDBatch(2.0, 15.0, 3.0, dt=1.0)
            plant.reset(0.0)
            pv = np.empty(n)
            for k in range(n):
                pv[k] = plant.output()[0]
                plant.step(np.array([op[k]]))
            pv += rng.normal(size=n) * 0.5 + np.cumsum(rng.normal(size=n)) * slow
            fit = foptd_fit.fit_windows([Window.of(np.arange(n, dtype=float), pv, op)])
            taus.append(np.log(fit.tau))
            ses.append(fit.tau_rse)
        return float(np.std(taus)), float(np.median(ses))

    white_scatter, white_se = fits(0.0)
    slow_scatter, slow_se = fits(0.3)
    assert 0.7 < white_se / white_scatter < 1.5
    assert slow_scatter > 10.0 * white_scatter
    assert slow_se > 0.25 * slow_scatter
    monkeypatch.setattr(  # the textbook form alone
        foptd_fit,
        "_covariance",
        lambda jac, r, noise, p, lags: np.linalg.inv(jac.T @ jac) * noise**2,
    )
    assert slow_se > 2.0 * fits(0.3)[1]


def test_the_integrating_alternative_finds_its_dead_time_from_a_coarse_grid():
    """A noise-free integrator (dead time 7.3 samples) searched from a grid whose
    nearest point is 7 samples off: the zoom finds the dead time within a twentieth of a
    sample and the residual far below the coarse grid's."""
    from service.engine.foptd_fit import Window, _integrating_fit

    rng = np.random.default_rng(3)
    n, theta, k = 300, 7.3, 0.02
    u = np.repeat(rng.normal(0.0, 1.0, n // 20), 20)
    t = np.arange(n, dtype=np.float64)
    # exact ZOH integration of u delayed by theta: interval [j, j+1) holds u[j-8] for
    # 0.3 of it and u[j-7] for the rest
    held = 0.3 * u[np.clip(np.arange(n) - 8, 0, None)] + 0.7 * u[np.clip(np.arange(n) - 7, 0, None)]
    pv = 5.0 + k * np.concatenate([[0.0], np.cumsum(held[:-1])])
    w = Window.of(t, pv, u)
    grid = np.append(np.linspace(0.0, 0.6 * w.span, 12), 0.0)
    sse, k_fit, theta_fit = _integrating_fit(w, grid)
    assert theta_fit == pytest.approx(theta, abs=0.05) and k_fit == pytest.approx(k, rel=1e-3)
    coarse = _integrating_fit(w, np.array([0.0]))  # (one point: no zoom beyond a sample)
    assert sse < 1e-4 * coarse[0]


@pytest.mark.parametrize("jitter", [0.2, 0.4])
def test_a_jittered_sample_clock_keeps_the_fits_grid_on_the_plants_time(jitter):
    """2000 samples 1 s +- ``jitter`` apart, registered at 1 s: every row sits within
    1.5 samples of its time on the fit's grid. Rounding each interval to samples alone
    let the grid drift from the clock: 10 s short at +-0.2 s (the period, then 0.83 s,
    made 1.2 s two samples) and, with the period right, 148 s long at +-0.4 s (0.2 s
    intervals were one sample)."""
    rng = np.random.default_rng(0)
    n = 2000
    t = np.sort(np.arange(n) + rng.uniform(-jitter, jitter, n))
    t[0] = 0.0
    w = recorded(t, np.zeros(n), np.zeros(n), registered=1.0)
    assert abs(w.dt - 1.0) < 0.05
    assert np.abs(w.rows * w.dt - t).max() < 1.5 * w.dt


def _jittered_loop(jitter: float, seed: int, n: int = 900):
    """A PI loop (kp 0.5, ki 0.5/40) on K 2, tau 40 s, theta 10 s, sampled every second
    give or take ``jitter`` (a polling gateway), the PI law run at each sample time and
    the plant solved exactly between the times its delayed input changes; noise 0.2,
    setpoint moves of 10 every 200 samples."""
    k, tau, theta = 2.0, 40.0, 10.0
    rng = np.random.default_rng(seed)
    t = np.sort(np.arange(n) + rng.uniform(-jitter, jitter, n))
    t[0] = 0.0
    sp = np.where((np.arange(n) // 200) % 2 == 1, 10.0, 0.0)
    pv, op = np.empty(n), np.empty(n)
    x = integral = u = now = 0.0
    arrivals = []  # (time the plant sees an output, the output)
    for i in range(n):
        while arrivals and arrivals[0][0] <= t[i]:  # to each change of the input
            at, new = arrivals.pop(0)
            x = k * u + (x - k * u) * np.exp(-(at - now) / tau)
            now, u = at, new
        x = k * u + (x - k * u) * np.exp(-(t[i] - now) / tau)
        now = t[i]
        pv[i] = x + 0.2 * rng.standard_normal()
        e = sp[i] - pv[i]
        integral += 0.5 / tau * e * (t[i] - t[i - 1] if i else 0.0)
        op[i] = 0.5 * e + integral
        arrivals.append((t[i] + theta, op[i]))
    return t, sp, pv, op


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_jittered_sample_clock_gives_the_plants_time_constant(seed):
    """Samples 1 s +-0.2 s apart (intervals 0.6-1.4 s), the loop registered at 1 s: tau
    within 2 % of 40 s and within 3 of its standard errors. The fit's period was the
    median of the intervals below 1.5x the shortest (0.81-0.83 s) and each interval was
    rounded to samples alone (1.2 s: 2): the model ran 11 % short of the plant's time,
    tau 34.6-35.7 s at 8-13 standard errors, and the model was confident."""
    from service.engine import identify
    from service.engine.foptd_fit import sample_period

    t, sp, pv, op = _jittered_loop(0.2, seed)
    assert abs(sample_period(t, 1.0) - 1.0) < 0.02
    starts = [int(i) for i in np.flatnonzero(np.diff(sp)) + 1]
    model = identify.assess(t, sp, pv, op, starts, registered=1.0).model
    error = np.log(model.tau / 40.0)
    assert abs(error) < 0.02 and abs(error) < 3.0 * model.tau_rse
    assert abs(model.k / 2.0 - 1.0) < 0.01 and abs(model.theta - 10.0) < 0.5
