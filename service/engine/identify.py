"""Closed-loop identification of a loop's process model: pure numerics, no engine state.

An *event* is a window of one loop's closed-loop data (sample times, setpoint,
measurement and controller output) that starts at a setpoint move and ends at the next
one (or when it grows too long). :func:`fit_event` fits a first-order-plus-dead-time
model from the controller output to the measurement over the window::

    pv(t) = b + K x(t),    tau x'(t) = u(t - theta) - u(t0) - x(t),    x(t0) = 0

(the plant at steady state when the window opens: the offset ``b`` absorbs the
operating point and, when the output is reconstructed from the PI law, the unknown
integral term). The fit is an output-error fit: the model is simulated from the
controller output alone, so measurement noise does not bias it as it would an
equation-error (ARX) fit, and the controller's reaction to noise is small where the
move is large against the noise (which the acceptance rules require).

Two steps: a grid over (tau, theta), each point linear in (K, b) and solved in closed
form, vectorised over the grid; then :func:`scipy.optimize.least_squares` refines the
best point over (K, log tau, theta, b). An integrating model ``K/s e^{-theta s}``
is fitted the same way and compared.

:func:`combine` turns the recent accepted events into one model with a confidence:
events must each fit well, see the response above the noise, pin down K and tau
(standard errors from the Jacobian), and agree with each other.

Sampling assumption: the samples are (near) uniform in time (the recorder's rows may
each be the mean of several: :func:`recorded`); the dead time is handled as a zero-order
hold sees it (:func:`_delayed`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import lfilter

MIN_SAMPLES = 12
"""Fewest samples in an event worth fitting."""
MIN_R2 = 0.75
"""Smallest share of the measurement's variance over the window the model must explain."""
MIN_SNR = 3.0
"""Smallest ratio of the modelled response (peak to peak) to the residual noise (rms)."""
MAX_REL_SE = 0.1
"""Largest relative standard error of K of the joint fit of a confident model."""
MAX_TAU_SE = 0.17
"""Largest relative standard error of tau: looser than K's, whose error is 2-10x smaller
on the same data (closed-loop data pin the gain down first; tau trades off against the
dead time). Measured on the bar's loops, seeds 0-2 (docs/identification.md): 0.15, 0.17,
0.20 identify 55-57, 57 and 58 of 60 from their first 4 moves."""
MAX_PREDICTION = 1.5
"""Consistency: the model of the earlier events must predict the last event's PV within
this many times the noise (rms)."""
PREDICTION_FLOOR = 0.01
"""Consistency on (nearly) noise-free data: the prediction error is counted against at
least this share of the typical move. There the residual is the linear model's own
error on a nonlinear plant, not noise, and its size depends on how the rows are
weighted: on the two-tank demo (noise 0) the earlier events' model predicted the third
with 0.02 cm, 2.3x the residual of 0.008 cm, and the model came 5 simulated minutes
later than with a prediction held to 0.2% of the 10 cm move. Under the bar's 1% noise
(moves of 5-25) the floor is below the noise and changes nothing."""
MIN_EVENTS = 2
"""Excited events needed for a confident model."""
IMPRECISE = "K or tau not pinned down"
"""The verdict of a model that passes every check but precision."""
DISAGREE = "events disagree"
"""The verdict of a precise model that fails only the consistency test (a drifting plant)."""
INTEGRATING_RATIO = 0.8
"""The integrating model wins when its residual sum of squares is below this share of
the FOPTD fit's, or within 10% of it while the FOPTD's tau runs beyond the window (a lag
that slow is an integrator as far as the data tell)."""

_TAU_GRID = 28
_THETA_GRID = 12
_FINE_TAU = 9


@dataclass
class EventFit:
    """One event (a setpoint move and the data up to the next) as identification saw it."""

    t0: float
    t1: float
    n: int
    move: float
    """The setpoint move that opened the event (engineering units, signed)."""
    snr: float = math.nan
    """Peak-to-peak response the model shows in the event, in multiples of the noise."""
    excited: bool = False

    def as_dict(self) -> dict:
        return {k: _num(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> EventFit:
        names = cls.__dataclass_fields__
        return cls(**{k: (math.nan if v is None else v) for k, v in d.items() if k in names})


@dataclass
class Model:
    """The FOPTD model of a segment and how far to trust it."""

    k: float
    tau: float
    theta: float
    noise: float
    """Residual rms (PV units): the measurement noise."""
    move: float
    """Typical setpoint move (median |move| of the excited events)."""
    r2: float
    k_rse: float
    tau_rse: float
    integrating: bool = False
    events: int = 0
    """Excited events the model comes from."""
    prediction: float = math.inf
    """Rms error (in noise units) with which the model of the earlier events predicts
    the last one."""
    confidence: float = 0.0
    """0..1: excitation x precision x consistency."""
    confident: bool = False

    def as_dict(self) -> dict:
        return {k: _num(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> Model:
        names = cls.__dataclass_fields__
        return cls(**{k: (math.inf if v is None else v) for k, v in d.items() if k in names})


@dataclass
class Assessment:
    events: list[EventFit]
    model: Model | None = None
    why: str = ""
    """Why the model is not confident ('' when it is)."""


def _num(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def reconstruct_op(t, e, kp, ki) -> np.ndarray:
    """The controller output of a parallel PI ``u = kp e + I``, ``I' = ki e`` (backward
    Euler on the sample times), bumpless on gain changes (a change of kp moves I so that
    u does not jump), from I = 0 at the first sample: the output up to a constant, which
    the fit's offset absorbs. Assumes the DCS runs the PI at (about) the sample period,
    with no feedforward, bias change or output tracking in the window."""
    t, e, kp, ki = (np.asarray(v, np.float64) for v in (t, e, kp, ki))
    dt = np.diff(t, prepend=t[:1])
    # bumpless: I jumps by -(kp_k - kp_{k-1}) e_{k-1} at a change of kp
    dkp = np.diff(kp, prepend=kp[:1])
    e_prev = np.concatenate([e[:1], e[:-1]])
    integral = np.cumsum(ki * e * dt - dkp * e_prev)
    return kp * e + integral


def _delayed(v: np.ndarray, tau: float, theta: np.ndarray, dt: float) -> np.ndarray:
    """The input each sample interval contributes, for each dead time (rows), exactly as a
    zero-order hold sees it: an interval [t_k, t_k+1) receives u[k-d-1] for its first
    f dt and u[k-d] for the rest (theta = (d + f) dt), weighted as the first-order lag
    integrates them, so that ``x[k+1] = a x[k] + (1 - a) w[k]``. Continuous in theta (as
    the optimiser needs) without blending the input's noise beyond what the plant does.
    Held at u[0] before the window."""
    theta = np.asarray(theta, np.float64).reshape(-1)
    n = v.size
    d = np.floor(theta / dt).astype(np.int64)
    f = theta / dt - d
    a = math.exp(-dt / tau)
    a1 = np.exp(-(1.0 - f) * dt / tau)
    w_old = (a1 - a) / (1.0 - a)
    k = np.arange(n)
    new = v[np.clip(k[None, :] - d[:, None], 0, n - 1)]
    old = v[np.clip(k[None, :] - d[:, None] - 1, 0, n - 1)]
    return new + w_old[:, None] * (old - new)


def _response(t, v, tau, theta, dt, integrating=False) -> np.ndarray:
    """x for one (tau, theta) (or the integral of the delayed input)."""
    if integrating:
        vd = _delayed(v, 1e12 * dt, np.array([theta]), dt)[0]
        return np.concatenate([[0.0], np.cumsum(vd[:-1]) * dt])
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
        # rows are contiguous: sums as differences of the running sum (np.add.reduceat
        # is several times slower on the grid search's (theta, 3, n) arrays)
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
    window's (b, K, c) (independent K per window: a start for the joint refinement)."""
    sse = np.zeros((len(taus), len(thetas)))
    for w in windows:
        steps = np.arange(w.t.size)
        for i, tau in enumerate(taus):
            vd = _delayed(w.v, tau, thetas, w.dt)  # (n_theta, n)
            a = math.exp(-w.dt / tau)
            x = lfilter([0.0, 1.0 - a], [1.0, -a], vd, axis=1)
            # pv = b + K x + c a^k (c: the plant not at rest when the window opens)
            basis = np.stack([np.ones_like(x), x, np.broadcast_to(a**steps, x.shape)], axis=1)
            basis = w.observe(basis, weighted=True).transpose(0, 2, 1)
            coef = _lstsq(basis, w.y)
            sse[i] += (((basis @ coef[:, :, None])[..., 0] - w.y[None, :]) ** 2).sum(axis=1)
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
    if start is not None and 0.05 * dt < start[0] < 20.0 * span and 0 <= start[1] < 0.9 * span:
        fit = _refine(windows, span, dt, *start)
        if fit.k > 0.0 and fit.r2 >= MIN_R2:
            return fit  # else: the grid search after all
    return _refine(windows, span, dt, *_grid(windows, span, dt))


def _refine(windows: list[Window], span: float, dt: float, tau0: float, theta0: float) -> Fit:
    m = len(windows)
    steps = [np.arange(w.t.size) for w in windows]

    def unpack(p):
        return p[0], math.exp(p[1]), p[2], p[3 : 3 + m], p[3 + m :]

    def residual(p):
        k, tau, theta, b, c = unpack(p)
        return np.concatenate(
            [
                w.observe(
                    b[i] + k * _response(w.t, w.v, tau, theta, w.dt)
                    + c[i] * np.exp(-w.dt * steps[i] / tau), weighted=True,
                ) - w.y
                for i, w in enumerate(windows)
            ]
        )  # fmt: skip

    # linear start for (K, b, c) at the grid's (tau, theta)
    starts = []
    for i, w in enumerate(windows):
        x = _response(w.t, w.v, tau0, theta0, w.dt)
        basis = np.stack([np.ones_like(x), x, np.exp(-w.dt * steps[i] / tau0)])
        starts.append(_lstsq(w.observe(basis, weighted=True).T[None], w.y)[0])
    starts = np.array(starts)
    k0 = float(np.median(starts[:, 1]))
    lo = [-np.inf, math.log(max(0.05 * dt, 1e-9)), 0.0] + [-np.inf] * (2 * m)
    hi = [np.inf, math.log(20.0 * span), 0.9 * span] + [np.inf] * (2 * m)
    p0 = np.concatenate([[k0, math.log(tau0), theta0], starts[:, 0], starts[:, 2]])
    p0 = np.clip(p0, np.add(lo, 1e-9), np.subtract(hi, 1e-9))
    pv_scale = [max(float(np.std(w.pv)), 1e-12) for w in windows]
    x_scale = [max(abs(k0), 1e-12), 1.0, max(dt, span / 20.0), *pv_scale, *pv_scale]
    res = least_squares(residual, p0, bounds=(lo, hi), x_scale=x_scale, max_nfev=100 + 20 * m)
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
        cov = np.linalg.inv(res.jac.T @ res.jac) * noise**2
        se = np.sqrt(np.maximum(np.diag(cov), 0.0))
        k_rse = float(se[0] / abs(k)) if k else math.inf
        tau_rse = float(se[1])  # log tau: relative
    except np.linalg.LinAlgError:
        k_rse = tau_rse = math.inf
    # the integrating alternative, pv = b + K int(u(t - theta)) dt + c t (c: the initial
    # slope), linear in (b, K, c) for each dead time of a grid (and the FOPTD's)
    sse_i = 0.0
    thetas = np.append(np.linspace(0.0, 0.6 * span, _THETA_GRID), theta)
    for w in windows:
        best = math.inf
        for th in thetas.tolist():
            xi = _response(w.t, w.v, 1.0, th, w.dt, integrating=True)
            basis = w.observe(np.stack([np.ones_like(xi), xi, w.t]), weighted=True).T
            coef = _lstsq(basis[None], w.y)[0]
            best = min(best, float(((basis @ coef - w.y) ** 2).sum()))
        sse_i += best
    integrating = sse_i < INTEGRATING_RATIO * sse or (tau > span and sse_i <= 1.1 * sse)
    return Fit(
        k=float(k), tau=tau, theta=float(theta),
        r2=1.0 - sse / sst if sst > 0 else 0.0,
        snr=float(np.ptp(np.concatenate(model))) / max(noise, 1e-300), noise=noise,
        k_rse=k_rse, tau_rse=tau_rse, integrating=bool(integrating), params=res.x,
        model=model,
    )  # fmt: skip


def _sst(w: Window) -> float:
    """The measurement's weighted sum of squares about its weighted mean."""
    y, s = w.y, (np.ones_like(w.pv) if w.count is None else np.sqrt(w.count))
    mean = float(y @ s) / float(s @ s)
    return float(((y - mean * s) ** 2).sum())


def screen(t, pv, op) -> str:
    """Why a window cannot be fitted at all ('' if it can)."""
    n = len(t)
    if n < MIN_SAMPLES:
        return f"too few samples ({n} < {MIN_SAMPLES})"
    t, pv, op = (np.asarray(x, np.float64) for x in (t, pv, op))
    if not (np.isfinite(t).all() and np.isfinite(pv).all() and np.isfinite(op).all()):
        return "non-finite data"
    if not (np.diff(t) > 0.0).all():  # a window of no duration: nothing to fit
        return "sample times not increasing (a new plant clock inside the segment)"
    if np.ptp(pv) == 0.0 or np.mean(np.diff(pv) == 0.0) > 0.5:
        return "measurement frozen (stuck transmitter?)"
    if np.ptp(op) == 0.0:
        return "controller output did not move"
    return ""


def recorded(t, pv, op, last: int = 1) -> Window:
    """The data as the fit sees them. Where the recorder halved its resolution
    (``service.engine.watch``: the rows around each move kept, the others each the mean
    measurement and output of the samples they stand for) a row spans ``count`` samples
    at the sample period h (its interval over h; the last row's: ``last``, which the
    recorder knows), its output is held over them (the mean input the plant saw) and the
    fit compares its mean measurement with the model's mean over its samples, weighted
    as the information it holds (:meth:`Window.observe`). Placing the means at the middle
    of their samples and interpolating them onto a uniform grid instead correlated the
    residuals and shrank them (0.56 sigma instead of a 2-sample mean's 0.71 on finely
    sampled loops): tau's standard error came out 20% too small. h is the median of the
    intervals below 1.5x the shortest (a gateway's jitter is not a halving)."""
    t, pv, op = (np.asarray(x, np.float64) for x in (t, pv, op))
    dt = np.diff(t)
    if last <= 1 and (dt.size == 0 or dt.max() - dt.min() <= 1e-6 * float(np.median(dt))):
        return Window.of(t, pv, op)
    h = float(np.median(dt[dt < 1.5 * dt.min()]))
    count = np.maximum(np.rint(np.append(dt / h, last)), 1).astype(np.int64)
    count[-1] = max(int(last), 1)
    rows = np.concatenate([[0], np.cumsum(count[:-1])])
    v = np.repeat(op - op[0], count)
    return Window(h * np.arange(v.size), pv, v, h, rows, count)


def assess(
    t, sp, pv, op, starts: list[int], start: tuple[float, float] | None = None, last: int = 1
) -> Assessment:
    """Identify from one contiguous segment of closed-loop data (no gap, manual or
    saturated sample inside) whose events (setpoint moves) start at the indices
    ``starts``; the last event runs to the end of the data. Rows may be the recorder's
    means of several samples (:func:`recorded`; ``last``: the samples the last row holds).

    One FOPTD model is fitted to the whole segment (one offset, one initial transient:
    far better determined than a fit per event). Each event is then judged by the
    response the model shows in it against the noise (a move too small for the noise
    excites nothing), and the model fitted without the last event must predict that
    event (consistency between events). Confident when :data:`MIN_EVENTS` events are
    excited, the fit explains the data (:data:`MIN_R2`), K and tau are pinned down
    (:data:`MAX_REL_SE`, :data:`MAX_TAU_SE`), the prediction holds (:data:`MAX_PREDICTION`) and an
    integrating model does not fit better.
    """
    t, sp, pv, op = (np.asarray(x, np.float64) for x in (t, sp, pv, op))
    bounds = [*starts, t.size]
    events = [
        EventFit(
            t0=float(t[a]), t1=float(t[b - 1]), n=b - a,
            move=float(sp[a] - sp[a - 1]) if a > 0 else 0.0,
        )
        for a, b in zip(bounds[:-1], bounds[1:], strict=True)
    ]  # fmt: skip
    out = Assessment(events=events)
    if len(starts) < MIN_EVENTS:
        out.why = f"waiting for setpoint moves ({len(starts)} of {MIN_EVENTS} seen)"
        return out
    # from the sample before the first move (the input at rest before it: the window's
    # first input is held before the window, so starting at the move would hide the
    # controller's proportional kick and bias tau up, K up and theta down)
    first = max(starts[0] - 1, 0)
    t, sp, pv, op = t[first:], sp[first:], pv[first:], op[first:]
    bounds = [b - first for b in bounds]
    out.why = screen(t, pv, op)
    if out.why:
        return out
    whole = recorded(t, pv, op, last)
    joint = fit_windows([whole], start)
    pred = joint.model[0]
    excited = 0
    for ev, a, b in zip(events, bounds[:-1], bounds[1:], strict=True):
        ev.snr = float(np.ptp(pred[a:b])) / max(joint.noise, 1e-300) if b > a else 0.0
        ev.excited = bool(ev.snr >= MIN_SNR)
        excited += ev.excited
    out.model = Model(
        k=joint.k, tau=joint.tau, theta=joint.theta, noise=joint.noise,
        move=float(np.median([abs(ev.move) for ev in events if ev.excited] or [0.0])),
        r2=joint.r2, k_rse=joint.k_rse, tau_rse=joint.tau_rse,
        integrating=joint.integrating, events=excited,
    )  # fmt: skip
    # consistency: the model of the data before the last excited event that has run the
    # model's theta + tau predicts it and what follows (a quiet event, or the first
    # samples of a new one, test next to nothing: docs/identification.md)
    shown = joint.theta + joint.tau
    tested = max(
        (i for i, ev in enumerate(events) if ev.excited and t[-1] - t[bounds[i]] >= shown),
        default=0,
    )
    cut = bounds[tested]
    if cut >= MIN_SAMPLES and excited >= MIN_EVENTS:
        early = fit_windows([whole.head(cut)], (joint.tau, joint.theta))
        b, c = early.params[3], early.params[4]
        miss = (predict(early.params, whole, b, c) - pv)[cut:]
        if whole.count is not None:  # in one sample's noise, as the residual
            miss = miss * np.sqrt(whole.count[cut:])
        rms = float(np.sqrt(np.mean(miss**2)))
        floor = PREDICTION_FLOOR * out.model.move
        out.model.prediction = rms / max(joint.noise, floor, 1e-300)
    out.why = _verdict(out.model, excited, len(events))
    m = out.model
    worst = max(m.k_rse / MAX_REL_SE, m.tau_rse / MAX_TAU_SE)
    precision = min(1.0, max(0.0, 1.5 - 0.5 * worst))
    consistency = min(1.0, max(0.0, (2.0 * MAX_PREDICTION - m.prediction) / MAX_PREDICTION))
    m.confidence = float(
        min(1.0, excited / MIN_EVENTS) * precision * consistency * (m.r2 >= MIN_R2)
    )
    m.confident = not out.why
    return out


def _verdict(m: Model, excited: int, n_events: int) -> str:
    if m.integrating:
        return "integrating: K/s e^(-theta s) fits better than an FOPTD model"
    if not m.k > 0.0:
        return (
            f"process gain {m.k:.3g} has the wrong sign for the registered controller "
            "action (the DCS block's action is probably the other one: register the loop "
            "again with the other 'action')"
        )
    if excited < MIN_EVENTS:
        return (
            f"move too small for the noise ({excited} of {n_events} events show a "
            f"response {MIN_SNR:g}x the noise {m.noise:.3g}; {MIN_EVENTS} needed)"
        )
    if m.r2 < MIN_R2:
        return f"poor fit (R2 {m.r2:.2f} < {MIN_R2:g})"
    if not (m.k_rse <= MAX_REL_SE and m.tau_rse <= MAX_TAU_SE):
        return f"{IMPRECISE} (rel. s.e. {m.k_rse:.2f}, {m.tau_rse:.2f})"
    if not m.prediction <= MAX_PREDICTION:
        return (
            f"{DISAGREE} (the earlier events' model predicts the last with "
            f"{m.prediction:.2f}x the noise)"
        )
    return ""
