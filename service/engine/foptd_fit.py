"""The output-error FOPTD fit behind :mod:`service.engine.identify`: the data as the fit
sees them (:class:`Window`, :func:`recorded`: full-resolution samples or the recorder's
means of several), the model's response with its dead time as a zero-order hold sees it,
a grid search over (tau, theta) linear in the rest, and the
:func:`scipy.optimize.least_squares` refinement with standard errors from the Jacobian;
an integrating model ``K/s e^{-theta s}`` fitted alongside. Pure numerics, no engine
state."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import lfilter

MIN_R2 = 0.75
"""Smallest share of the measurement's variance over the window the model must explain."""
INTEGRATING_RATIO = 0.8
"""The integrating model wins when its residual sum of squares is below this share of
the FOPTD fit's, or within 10% of it while the FOPTD's tau runs beyond the window (a lag
that slow is an integrator as far as the data tell)."""

_EPS_STEP = math.sqrt(np.finfo(np.float64).eps)
"""Relative step of the forward differences in log tau and theta (scipy's '2-point')."""
_TAU_GRID = 28
_THETA_GRID = 12
_FINE_TAU = 9
_THETA_MAX = 0.9
"""Largest dead time fitted, as a share of the window's span."""
_TAU_MAX = 20.0
"""Largest time constant fitted, in window spans (a slower lag is an integrator as far as
the data tell)."""
_THETA_RESOLUTION = 0.05
"""Finest step of the integrating alternative's dead time, in samples."""


def _delayed(v: np.ndarray, tau: float, theta: np.ndarray, dt: float) -> np.ndarray:
    """The input each sample interval contributes, for each dead time (rows), exactly as a
    zero-order hold sees it: an interval [t_k, t_k+1) receives u[k-d-1] for its first
    f dt and u[k-d] for the rest (theta = (d + f) dt), weighted as the first-order lag
    integrates them, so that ``x[k+1] = a x[k] + (1 - a) w[k]`` (``tau`` inf: an
    integrator, the weights f and 1 - f). Continuous in theta (as the optimiser needs)
    without blending the input's noise beyond what the plant does. Held at u[0] before
    the window."""
    theta = np.asarray(theta, np.float64).reshape(-1)
    n = v.size
    d = np.floor(theta / dt).astype(np.int64)
    f = theta / dt - d
    if math.isinf(tau):
        w_old = f
    else:
        a = math.exp(-dt / tau)
        w_old = (np.exp(-(1.0 - f) * dt / tau) - a) / (1.0 - a)
    k = np.arange(n)
    new = v[np.clip(k[None, :] - d[:, None], 0, n - 1)]
    old = v[np.clip(k[None, :] - d[:, None] - 1, 0, n - 1)]
    return new + w_old[:, None] * (old - new)


def _response(t, v, tau, theta, dt) -> np.ndarray:
    """x for one (tau, theta)."""
    vd = _delayed(v, tau, np.array([theta]), dt)[0]
    a = math.exp(-dt / tau)
    return lfilter([0.0, 1.0 - a], [1.0, -a], vd)


@dataclass
class Window:
    """One stretch of data: the output on a uniform grid of sample times (times relative
    to its start, the output relative to its first value: a reconstructed output is
    known only up to a constant) and the measurement as recorded, one value per grid
    sample, or per recorder row where the recorder halved its resolution: row r the mean
    of ``count[r]`` grid samples from ``rows[r]`` on."""

    t: np.ndarray
    pv: np.ndarray
    v: np.ndarray
    dt: float
    rows: np.ndarray | None = None
    count: np.ndarray | None = None

    @classmethod
    def of(cls, t, pv, op) -> Window:
        t, pv, op = (np.asarray(x, np.float64) for x in (t, pv, op))
        return cls(t - t[0], pv, op - op[0], float(np.median(np.diff(t))))

    @property
    def span(self) -> float:
        return float(self.t[-1])

    def observe(self, x: np.ndarray, weighted: bool = False) -> np.ndarray:
        """A model's grid series ``(..., n)`` as recorded ``(..., m)``: each row's mean;
        ``weighted``: times sqrt(count), so that every residual has one sample's noise
        (a mean of s samples has 1/s of its variance) and least squares weighs the rows
        as the information they hold."""
        if self.rows is None:
            return x
        # rows are contiguous: sums as differences of the running sum
        total = np.diff(
            np.cumsum(x, axis=-1)[..., self.rows + self.count - 1], axis=-1, prepend=0.0
        )
        return total / (np.sqrt(self.count) if weighted else self.count)

    @property
    def y(self) -> np.ndarray:
        """The measurement, weighted as :meth:`observe` ``weighted``."""
        return self.pv if self.rows is None else self.pv * np.sqrt(self.count)

    def head(self, cut: int) -> Window:
        """The first ``cut`` rows."""
        if self.rows is None:
            return Window(self.t[:cut], self.pv[:cut], self.v[:cut], self.dt)
        n = int(self.rows[cut])
        return Window(
            self.t[:n], self.pv[:cut], self.v[:n], self.dt, self.rows[:cut], self.count[:cut]
        )


def _lstsq(basis: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares of y on each (n, j) basis of a batch (g, n, j), via normal equations."""
    bt = basis.transpose(0, 2, 1)
    ata = bt @ basis + 1e-12 * np.eye(basis.shape[2])
    return np.linalg.solve(ata, bt @ y[:, None])[..., 0]


def _sse_grid(windows: list[Window], taus, thetas) -> np.ndarray:
    """Residual sum of squares at each (tau, theta) of a grid, each point linear in every
    window's (b, K, c) (independent K per window: a start for the joint refinement).

    One filter pass per tau: the lag is linear and time-invariant and the input is at rest
    (0) before the window, so the response to the input delayed by theta = (d + f) dt is
    the undelayed response shifted by d and d + 1 samples, blended as :func:`_delayed`
    blends the input; a recorded row's sum of it is a difference of the running sum. An
    input offset only adds ``c (1 - a^k)``, which b and c absorb."""
    thetas = np.asarray(thetas, np.float64)
    sse = np.zeros((len(taus), thetas.size))
    for w in windows:
        n = w.t.size
        rows = np.arange(n) if w.rows is None else w.rows
        count = np.ones(n, np.int64) if w.count is None else w.count
        root = np.sqrt(count)
        d = np.floor(thetas / w.dt).astype(np.int64)
        f = thetas / w.dt - d
        # running-sum indices of each row's first and one-past-last sample, delayed by d
        # (and d + 1); before the window the response is 0
        lo = np.clip(rows[None, :] - d[:, None], 0, n)
        hi = np.clip((rows + count)[None, :] - d[:, None], 0, n)
        lo1, hi1 = np.maximum(lo - 1, 0), np.maximum(hi - 1, 0)
        ones = root  # the offset b, as recorded (weighted row sums of 1)
        y = w.y
        steps = np.arange(n)
        v = w.v - w.v[0]
        for i, tau in enumerate(taus):
            a = math.exp(-w.dt / tau)
            run = np.concatenate([[0.0], np.cumsum(lfilter([0.0, 1.0 - a], [1.0, -a], v))])
            w_old = (np.exp(-(1.0 - f) * w.dt / tau) - a) / (1.0 - a)
            x = (run[hi] - run[lo]) + w_old[:, None] * ((run[hi1] - run[lo1]) - (run[hi] - run[lo]))
            x /= root
            decay = np.concatenate([[0.0], np.cumsum(a**steps)])
            g = (decay[rows + count] - decay[rows]) / root  # the transient c a^k
            # the normal equations of (b, K, c) for every theta at once
            xo, xg, xx = x @ ones, x @ g, (x * x).sum(axis=1)
            const = np.ones_like(xo)
            gram = np.stack(
                [
                    np.stack([(ones @ ones) * const, xo, (ones @ g) * const], axis=-1),
                    np.stack([xo, xx, xg], axis=-1),
                    np.stack([(ones @ g) * const, xg, (g @ g) * const], axis=-1),
                ],
                axis=-2,
            )
            gram += 1e-12 * np.eye(3)
            rhs = np.stack([(ones @ y) * const, x @ y, (g @ y) * const], axis=-1)
            coef = np.linalg.solve(gram, rhs[..., None])[..., 0]
            r = y - coef[:, :1] * ones - coef[:, 1:2] * x - coef[:, 2:] * g
            sse[i] += (r * r).sum(axis=1)
    return sse


def _grid(windows: list[Window], span: float, dt: float) -> tuple[float, float]:
    """Best (tau, theta): a coarse log/linear grid over the whole range, then a fine one
    around its best point, theta in steps of half a sample (the residual is rippled in
    theta at the sample period: the optimiser alone stops in the nearest ripple, up to
    10 noise variances above the best fit, with tau 30-40% off)."""
    taus = np.geomspace(max(0.2 * dt, 1e-9), 4.0 * span, _TAU_GRID)
    thetas = np.linspace(0.0, 0.6 * span, _THETA_GRID)
    i, j = np.unravel_index(
        int(np.argmin(_sse_grid(windows, taus, thetas))), (taus.size, thetas.size)
    )
    step = thetas[1] - thetas[0]
    taus = taus[i] * np.geomspace(0.6, 1.7, _FINE_TAU)
    thetas = np.arange(max(thetas[j] - 2.0 * step, 0.0), thetas[j] + 2.0 * step, 0.5 * dt)
    sse = _sse_grid(windows, taus, thetas)
    i, j = np.unravel_index(int(np.argmin(sse)), sse.shape)
    return float(taus[i]), float(thetas[j])


@dataclass
class Fit:
    k: float
    tau: float
    theta: float
    r2: float
    snr: float
    noise: float
    k_rse: float
    tau_rse: float
    integrating: bool
    params: np.ndarray
    """(K, log tau, theta, b_1.., c_1..) as fitted (to predict other data)."""
    model: list[np.ndarray]
    """The model's pv over each window (as recorded: row means)."""
    slope: float = 0.0
    """The integrating alternative's K (PV units per output unit per second), of the first
    window (identification fits one)."""
    theta_i: float = 0.0
    """Its dead time (s)."""
    lag_rse: float = math.inf
    """Relative standard error of tau + theta (the lag a slow ramp shows, whose split it
    does not: :data:`service.engine.identify.LUMP_THETA`)."""


def predict(params: np.ndarray, w: Window, b: float, c: float) -> np.ndarray:
    """The pv an FOPTD fit predicts over a window (as recorded: row means), given that
    window's b and c."""
    k, tau, theta = params[0], math.exp(params[1]), params[2]
    steps = np.arange(w.t.size)
    x = k * _response(w.t, w.v, tau, theta, w.dt) + c * np.exp(-w.dt * steps / tau)
    return b + w.observe(x)


def fit_windows(windows: list[Window], start: tuple[float, float] | None = None) -> Fit:
    """Least-squares FOPTD fit shared by the windows (each with its own offset b and
    initial transient c): :func:`scipy.optimize.least_squares` from a grid search's best
    (tau, theta), or from ``start`` (a model already known)."""
    span = max(w.span for w in windows)
    dt = float(np.median([w.dt for w in windows]))
    if not (span > 0.0 and dt > 0.0):  # screen() keeps such windows out of assess()
        raise ValueError(f"degenerate window (span {span}, dt {dt}): nothing to fit")
    fits = 0 <= start[1] < _THETA_MAX * span if start is not None else False
    if fits and 0.05 * dt < start[0] < _TAU_MAX * span:
        fit = _refine(windows, span, dt, *start)
        if fit.k > 0.0 and fit.r2 >= MIN_R2:
            return fit  # else: the grid search after all
    return _refine(windows, span, dt, *_grid(windows, span, dt))


def _refine(windows: list[Window], span: float, dt: float, tau0: float, theta0: float) -> Fit:
    m = len(windows)
    steps = [np.arange(w.t.size) for w in windows]

    def unpack(p):
        return p[0], math.exp(p[1]), p[2], p[3 : 3 + m], p[3 + m :]

    def parts(tau, theta):
        """Each window's response x and initial transient's decay at (tau, theta)."""
        return [
            (_response(w.t, w.v, tau, theta, w.dt), np.exp(-w.dt * steps[i] / tau))
            for i, w in enumerate(windows)
        ]

    def residual(p):
        k, tau, theta, b, c = unpack(p)
        return np.concatenate(
            [
                w.observe(b[i] + k * x + c[i] * g, weighted=True) - w.y
                for i, (w, (x, g)) in enumerate(zip(windows, parts(tau, theta), strict=True))
            ]
        )

    def jacobian(p):
        """Exact in the linear parameters (K, b, c); forward differences in log tau and
        theta with scipy's 2-point steps (a filter pass each instead of one per
        parameter)."""
        k, tau, theta, b, c = unpack(p)
        h = _EPS_STEP * np.where(p[1:3] >= 0.0, 1.0, -1.0) * np.maximum(1.0, np.abs(p[1:3]))
        h = np.where(p[1:3] + h > np.array(hi[1:3]), -h, h)  # stay inside the bounds
        here = parts(tau, theta)
        slower = parts(tau * math.exp(h[0]), theta)
        later = parts(tau, theta + h[1])
        blocks = []
        for i, w in enumerate(windows):
            (x, g), (x_t, g_t), (x_d, _) = here[i], slower[i], later[i]
            col = np.zeros((w.pv.size, p.size))
            col[:, 0] = w.observe(x, weighted=True)
            col[:, 1] = w.observe(k * (x_t - x) + c[i] * (g_t - g), weighted=True) / h[0]
            col[:, 2] = w.observe(k * (x_d - x), weighted=True) / h[1]
            col[:, 3 + i] = w.observe(np.ones_like(x), weighted=True)
            col[:, 3 + m + i] = w.observe(g, weighted=True)
            blocks.append(col)
        return np.vstack(blocks)

    # linear start for (K, b, c) at the grid's (tau, theta)
    starts = []
    for i, w in enumerate(windows):
        x = _response(w.t, w.v, tau0, theta0, w.dt)
        basis = np.stack([np.ones_like(x), x, np.exp(-w.dt * steps[i] / tau0)])
        starts.append(_lstsq(w.observe(basis, weighted=True).T[None], w.y)[0])
    starts = np.array(starts)
    k0 = float(np.median(starts[:, 1]))
    lo = [-np.inf, math.log(max(0.05 * dt, 1e-9)), 0.0] + [-np.inf] * (2 * m)
    hi = [np.inf, math.log(_TAU_MAX * span), _THETA_MAX * span] + [np.inf] * (2 * m)
    p0 = np.concatenate([[k0, math.log(tau0), theta0], starts[:, 0], starts[:, 2]])
    p0 = np.clip(p0, np.add(lo, 1e-9), np.subtract(hi, 1e-9))
    pv_scale = [max(float(np.std(w.pv)), 1e-12) for w in windows]
    x_scale = [max(abs(k0), 1e-12), 1.0, max(dt, span / 20.0), *pv_scale, *pv_scale]
    res = least_squares(
        residual, p0, jac=jacobian, bounds=(lo, hi), x_scale=x_scale, max_nfev=100 + 20 * m
    )
    k, tau, theta, _b, _c = unpack(res.x)
    r = res.fun
    n = r.size
    sse = float(r @ r)  # in one sample's noise (rows weighted)
    sst = sum(_sst(w) for w in windows)
    noise = math.sqrt(sse / max(n - res.x.size, 1))
    split = np.cumsum([w.pv.size for w in windows])[:-1]
    model = [w.pv + ri / np.sqrt(1.0 if w.count is None else w.count)
             for w, ri in zip(windows, np.split(r, split), strict=True)]  # fmt: skip
    try:
        cov = _covariance(res.jac, r, noise, res.x.size, _lags(span, n, tau + theta))
        se = np.sqrt(np.maximum(np.diag(cov), 0.0))
        k_rse = float(se[0] / abs(k)) if k else math.inf
        tau_rse = float(se[1])  # log tau: relative
        # d(tau + theta) = tau d(log tau) + d theta
        lag_var = tau * tau * cov[1, 1] + cov[2, 2] + 2.0 * tau * cov[1, 2]
        lag_rse = math.sqrt(max(float(lag_var), 0.0)) / (tau + theta)
    except np.linalg.LinAlgError:
        k_rse = tau_rse = lag_rse = math.inf
    thetas = np.append(np.linspace(0.0, 0.6 * span, _THETA_GRID), theta)
    alternative = [_integrating_fit(w, thetas) for w in windows]
    sse_i = sum(a[0] for a in alternative)
    integrating = sse_i < INTEGRATING_RATIO * sse or (tau > span and sse_i <= 1.1 * sse)
    return Fit(
        k=float(k), tau=tau, theta=float(theta),
        r2=1.0 - sse / sst if sst > 0 else 0.0,
        snr=float(np.ptp(np.concatenate(model))) / max(noise, 1e-300), noise=noise,
        k_rse=k_rse, tau_rse=tau_rse, integrating=bool(integrating), params=res.x,
        model=model, slope=alternative[0][1], theta_i=alternative[0][2], lag_rse=lag_rse,
    )  # fmt: skip


def _integrating_fit(w: Window, thetas: np.ndarray) -> tuple[float, float, float]:
    """(residual sum of squares, K, theta) of the integrating alternative over window
    ``w``, ``pv = b + K int(u(t - theta)) dt + c t`` (c: the initial slope), linear in
    (b, K, c) for each dead time: the best of the grid ``thetas`` (the FOPTD's dead time
    among them), then zoomed in: 33 dead times over one grid step either way of it, and
    again over two of the new steps either way, down to :data:`_THETA_RESOLUTION` of a
    sample, each a vectorised pass. Why the zoom: the residual is rippled in theta at the
    sample period and, on a loop with little noise, sharp (an integrator with a dead time
    of 15 samples, no noise: 0.0007 there, 3.3 half a sample off, 13 a sample off), so
    at the grid's dead times and the FOPTD's (half a sample off: its tau at its bound,
    the dead time makes up for the lag it cannot drop) it came out 5x the FOPTD's, and
    the process was taken for an imprecise FOPTD instead of an integrator
    (docs/identification.md, Integrating processes)."""
    top = _THETA_MAX * w.span
    grid = np.clip(np.asarray(thetas, np.float64), 0.0, top)
    half = float(np.max(np.diff(np.sort(grid)))) if grid.size > 1 else w.dt
    # (b, c) are the same columns at every dead time: project them out once
    # (Frisch-Waugh-Lovell), leaving K's one column per dead time
    q = np.linalg.qr(w.observe(np.stack([np.ones_like(w.t), w.t]), weighted=True).T)[0]
    y = w.y - q @ (q.T @ w.y)
    while True:
        vd = _delayed(w.v, math.inf, grid, w.dt)
        xi = np.concatenate([np.zeros((grid.size, 1)), np.cumsum(vd[:, :-1], axis=1) * w.dt], 1)
        x = w.observe(xi, weighted=True)
        x -= (x @ q) @ q.T
        ks = (x @ y) / np.maximum((x * x).sum(axis=1), 1e-300)
        sse = ((y - ks[:, None] * x) ** 2).sum(axis=1)
        j = int(np.argmin(sse))
        best, value, k = float(grid[j]), float(sse[j]), float(ks[j])
        step = max(half / 16.0, _THETA_RESOLUTION * w.dt)
        if half <= _THETA_RESOLUTION * w.dt:
            return value, k, best
        grid = np.unique(np.clip(best + step * np.arange(-16, 17), 0.0, top))
        half = 2.0 * step if step > _THETA_RESOLUTION * w.dt else 0.0


def _lags(span: float, rows: int, shown: float) -> int:
    """Lags of :func:`_covariance`: the rows the model's response (``shown`` = tau + theta)
    spans on average, at most a quarter of them."""
    return int(min(max(1, round(shown * rows / max(span, 1e-300))), rows // 4))


def _covariance(jac: np.ndarray, r: np.ndarray, noise: float, p: int, lags: int) -> np.ndarray:
    """The parameters' covariance: the larger, entry by entry, of the textbook
    ``(J'J)^-1 noise^2`` and the Newey-West (Bartlett-weighted, ``lags``) sandwich
    ``B S B``, ``B = (J'J)^-1``, ``S`` the residual-weighted Jacobian's autocovariance up
    to ``lags``. The textbook form assumes white residuals; a linear model of a real
    loop leaves slow ones (its own error, an output reconstructed from the PI law), and
    then tau's error is several times what it gives: on dead-time dominant loops of the
    long robustness run tau scattered 58-68 s for 60 s at 0.7 % (docs/identification.md).
    ``p``: fitted parameters (the small-sample factor)."""
    bread = np.linalg.inv(jac.T @ jac)
    g = jac * r[:, None]
    meat = g.T @ g
    for lag in range(1, lags + 1):
        c = g[lag:].T @ g[:-lag]
        meat += (1.0 - lag / (lags + 1)) * (c + c.T)
    n = r.size
    sandwich = bread @ meat @ bread * (n / max(n - p, 1))
    return np.maximum(sandwich, bread * noise**2)


def _sst(w: Window) -> float:
    """The measurement's weighted sum of squares about its weighted mean."""
    y, s = w.y, (np.ones_like(w.pv) if w.count is None else np.sqrt(w.count))
    mean = float(y @ s) / float(s @ s)
    return float(((y - mean * s) ** 2).sum())


def recorded(t, pv, op, last: int = 1, registered: float = 0.0) -> Window:
    """The data as the fit sees them. Where the recorder halved its resolution
    (``service.engine.watch``: the rows around each move kept, the others each the mean
    measurement and output of the samples they stand for) a row spans ``count`` samples
    at the sample period h (its interval over h; the last row's: ``last``, which the
    recorder knows), its output is held over them (the mean input the plant saw) and the
    fit compares its mean measurement with the model's mean over its samples, weighted
    as the information it holds (:meth:`Window.observe`). Placing the means at the middle
    of their samples and interpolating them onto a uniform grid instead correlated the
    residuals and shrank them (0.56 sigma instead of a 2-sample mean's 0.71 on finely
    sampled loops): tau's standard error came out 20% too small."""
    t, pv, op = (np.asarray(x, np.float64) for x in (t, pv, op))
    dt = np.diff(t)
    if last <= 1 and (dt.size == 0 or dt.max() - dt.min() <= 1e-6 * float(np.median(dt))):
        return Window.of(t, pv, op)
    h = sample_period(t, registered)  # (``registered``: see sample_period)
    # each row starts at the grid sample nearest its time (later than the row before's):
    # rounding each interval alone drifted the grid off a jittered clock (intervals of
    # 0.6-1.4 s, h 0.83 s: rows of 1.2 s were 2 samples, the grid ran 11 % short, tau 10 %)
    near = np.rint((t - t[0]) / h).astype(np.int64)
    steps = np.arange(near.size)
    rows = np.maximum.accumulate(near - steps) + steps
    count = np.append(np.diff(rows), max(int(last), 1))
    v = np.repeat(op - op[0], count)
    return Window(h * np.arange(v.size), pv, v, h, rows, count)


_PERIOD_ROUNDS = 8
"""Refinements of :func:`sample_period`'s median at most (it settles in 2-4)."""
SHORTEST = 0.5
"""Share of the usual interval (:func:`sample_period`) below which an interval between
two rows is not the sample period."""


def sample_period(t, registered: float = 0.0) -> float:
    """The sample period of recorded rows' times ``t`` (some rows the means of several
    samples): the median of the shortest intervals, those within 50 % of it (the
    intervals between single samples; rows of two or more lie beyond), found from the
    median of those below 1.5x the shortest and refined until it holds. A gateway's
    jitter spreads single samples' intervals (+-0.2 s on 1 s: 0.6-1.4 s): the median
    below 1.5x the shortest alone was 0.83 s, and the fit's grid 11 % short of the
    plant's time (tau too, confident). Given the loop's ``registered`` sample period,
    intervals below :data:`SHORTEST` of the lesser of it and the recorded intervals'
    lower quartile (a gateway may sample faster than registered; a move's first rows are
    single samples) are left out: one sample sent right after another made h that
    interval, and every row as many samples as it would hold (session 38's review: one
    interval of 0.01 s in rows of 4 s cost a fit 46 s of CPU and 0.9 GB, and read the
    noise 20x too high)."""
    dt = np.diff(np.asarray(t, np.float64))
    if registered > 0.0 and dt.size:
        kept = dt[dt >= SHORTEST * min(registered, float(np.quantile(dt, 0.25)))]
        dt = kept if kept.size else dt
    h = float(np.median(dt[dt < 1.5 * dt.min()]))
    for _ in range(_PERIOD_ROUNDS):
        near = dt[(dt > 0.5 * h) & (dt < 1.5 * h)]
        h, was = float(np.median(near)), h
        if abs(h - was) <= 1e-9 * was:
            break
    return h
