"""Mapping a plant loop into the agent's units: the paper's section 5.4 recipe.

The agent was trained on FOPTD plants with gain K in [0.25, 1], time constant tau in
[0.25, 1] (dimensionless time units) and errors of order 1. A real loop is made to look
like one of those by three factors, derived from a crude model hint (process gain
``k_hat`` and time constant ``tau_hat`` in engineering units) and a PV scale:

* error scale ``e_scale`` (agent error per engineering error) = 1 / pv_scale. The paper
  subtracts the 55 cm operating point and divides by 10 cm; the offset cancels in an
  error, so only the division remains.
* output scale ``u_scale`` (agent controller output per engineering output)
  = e_scale * k_hat / 0.5, so that the hinted plant appears with gain 0.5, the
  geometric centre of the training range; a hint wrong by 0.5x-2x still lands inside.
  A plant of true gain K appears as K * e_scale / u_scale.
* time unit ``time_unit_s`` (seconds per agent time unit) = tau_hat / 0.5, so the
  hinted time constant appears as 0.5; a true tau appears as tau / time_unit_s.

A PI controller u = kp e + ki int(e dt) then maps between the two unit systems as

    kp_eng = kp_agent * e_scale / u_scale
    ki_eng = ki_agent * e_scale / (u_scale * time_unit_s)        (ki_eng per second)

and the agent's integral state is int(e_agent dt_agent) = e_scale / time_unit_s times
the integral of the engineering error over seconds. One RL step (one gain update) is
:data:`RL_STEP_AGENT_UNITS` agent time units, i.e. ``RL_STEP_AGENT_UNITS * time_unit_s``
seconds of plant time.

Paper example (two tanks): hint 1.2 cm/(L/min), 30 s; PV scale 10 cm. Then
e_scale = 0.1, the hint appears as 0.12 before and 0.5 after output scaling
(u_scale = 0.24, i.e. the agent's output is multiplied by 0.5/0.12 on its way to the
plant), the true gain 1.7 appears as 0.71, one agent time unit is 60 s, and the true
55 s time constant appears as 0.92.
"""

from __future__ import annotations

from typing import Annotated, NamedTuple

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    ValidationError,
    field_validator,
    model_validator,
)

AGENT_GAIN = 0.5
"""Process gain at which a hinted loop appears to the agent."""
AGENT_TAU = 0.5
"""Time constant (agent units) at which a hinted loop appears to the agent."""
RL_STEP_AGENT_UNITS = 2.75
"""Agent time units between two RL steps (gain updates), as in training."""
AGENT_KP0 = AGENT_KI0 = 0.05
"""The paper's deliberately slow initial tuning (Kc = 0.05, tau_I = 1), agent units."""
AGENT_GAIN_RANGE = (0.01, 50.0)
"""Default bounds of kp and ki in agent units. Training clips the gains to
[``service.agent.GAIN_FLOOR`` = 0.001, 50]: the upper bound is training's, the lower one
keeps a tuned loop an order of magnitude above the floor."""
DEFAULT_FORGETTING = 0.99
"""The paper's forgetting factor gamma of the hidden state, used online."""

PAPER_MOVE = 2.0
"""Size of a setpoint move in the paper's training protocol (a +-1 square wave), agent units.
The agent sees the error and its integral scaled by PAPER_MOVE / (the last move's size):
a linear loop answers a move of any size with the same shape, and this makes it the
shape of the moves the agent was trained on (docs/tuner.md, "Setpoint-move scaling")."""
OBS_GAIN_RANGE = (0.25, 4.0)
"""Bounds of that scaling: moves from 0.5 to 8 agent units are scaled exactly; a smaller
one is not blown up into noise, a larger one not shrunk to 0."""
MOVE_STEP = 0.2
"""Smallest setpoint change that counts as a move, agent units (the default of a loop's
``excitation_min_step``; training uses it too)."""
EXCITATION_PERIODS = 4.0
"""The excitation gate's window, RL periods: a loop is stepped only in the RL periods that
end within this many periods of a setpoint move (the default of a loop's
``excitation_periods``; training with ``excitation_gate`` uses it too). 4, the paper's
protocol (a move every 4 periods), so on a held setpoint the agent stops where its
training's core responses end: with 5, v3 drifted on the settled fifth period (setpoint
held 22 time units: worst 0.038 -> 0.020 with 4; 3 cuts v2 and v3 off their sequence,
docs/tuner.md, Robustness measures 6)."""


OBS_WINDOW = 0.2
"""Share of the RL period whose samples the agent's error observation averages: e is the
mean of the measured error over the samples at times due - OBS_WINDOW * period <= t <
due, ``due`` the end of the RL period (:func:`error_window`)."""


def error_window(e, t, due, period, total, count, window_due):
    """One sample of the agent's error observation, vectorised over loops (arrays (n,)).

    Adds the error ``e`` measured at time ``t`` to the running sum ``total`` and count
    ``count`` of the samples in the observation window of the RL period ending at ``due``
    (length ``period``; any one clock): due - OBS_WINDOW * period <= t < due. The sample
    at ``due`` itself is not in it: it opens the next period, and a setpoint moved exactly
    there belongs to the next period's response (training's setpoint changes take effect
    from the first sample of an RL period). The sums belong to the period ending at
    ``window_due``; a sample of another period (the decimation restarted, or the last
    period ended) starts them afresh. Returns (total, count); the observation at the
    period's end is :func:`window_error`. The engine calls it per sample
    (service.engine.rules), training per controller sample (service.learn.env), so both
    compute the same number."""
    ours = window_due == due
    inside = (t >= due - OBS_WINDOW * period) & (t < due)
    total = np.where(ours, total, 0.0) + np.where(inside, e, 0.0)
    return total, np.where(ours, count, 0.0) + inside


def window_error(total, count, e, due, period, last_move):
    """The agent's error observation at the end of an RL period (``due``): the mean over
    the window (:func:`error_window`), or the error ``e`` of the sample at the period's
    end where the window holds no sample (samples sparser than OBS_WINDOW of the period)
    or the setpoint moved inside it (``last_move``, the time of the last move, same
    clock): a mean across a move mixes the error before it with the response after it,
    a number the agent never saw in training; such a period's error is the response,
    not noise. With white noise of sigma per sample the mean's noise is sigma /
    sqrt(count): 33 samples at 1 s for a 165 s RL period (the two-tank scaling), 5.7x
    less noise than one sample."""
    start = due - OBS_WINDOW * period
    mixed = (last_move >= start) & (last_move < due)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where((count > 0) & ~mixed, total / count, e)


RAMP_GAP = 4
"""Samples between two changes of one setpoint ramp at most: a change in the direction of
the last, within this many samples of it, continues a ramp (a DCS ramp or a setpoint rate
limit changes the setpoint every scan; a gateway may poll a few times a scan). An
operator's steps seconds or minutes apart are steps, each with its own response."""


RAMP_LONG = 1.0
"""RL periods a ramp must run (first change to last) for the RL period after its last
change to be skipped as well: after a shorter one the loop answers as after a step, and
the agent learns from that period (skipping it left ramps over 0.2-0.5 RL periods at a
worst step-test MSE of 0.08-0.10 instead of 0.006-0.012: docs/tuner.md)."""


class Ramp(NamedTuple):
    """The setpoint-ramp rule's verdicts over a block of samples and its carried state."""

    changed: np.ndarray
    """(n, m) bool: the setpoint changed at the sample."""
    continues: np.ndarray
    """(n, m) bool: the sample's setpoint change continued a ramp (not its first change)."""
    last: np.ndarray
    """(n,) the last setpoint seen (NaN: none yet)."""
    way: np.ndarray
    """(n,) the sign of the last change (NaN: none)."""
    since: np.ndarray
    """(n,) samples since the last change."""


def ramp_rule(sp, last, way, since) -> Ramp:
    """The setpoint-ramp rule over the next ``m`` samples of ``n`` loops, vectorised:
    ``sp`` (n, m) the setpoints (NaN: a sample without one, which changes nothing),
    ``last``, ``way``, ``since`` (n,) as returned for the previous block. A change of the
    setpoint continues a ramp when it goes the way of the previous change and comes at
    most :data:`RAMP_GAP` samples after it. A ramp is not a series of steps: the agent is
    not stepped while one runs (service.engine.rules) and identification takes it as one
    event (service.engine.watch). The engine calls it per sample (m = 1), training per
    RL period (service.learn.env), so both compute the same."""
    n, m = sp.shape
    full = np.concatenate([np.asarray(last, np.float64)[:, None], sp], axis=1)
    cols = np.arange(m + 1)
    seen = np.maximum.accumulate(np.where(np.isnan(full), 0, cols), axis=1)
    full = np.take_along_axis(full, seen, axis=1)  # a sample without one keeps the last
    with np.errstate(invalid="ignore"):
        d = np.diff(full, axis=1)
        changed = np.abs(d) > 0.0  # False for NaN: the first setpoint is no change
    j = cols[:m].astype(np.float64)
    # each sample's previous change (the carried one at -1 - since) and its direction
    at = np.concatenate([(-1.0 - since)[:, None], np.where(changed, j, -np.inf)], axis=1)
    at = np.maximum.accumulate(at, axis=1)
    ways = np.concatenate([np.asarray(way, np.float64)[:, None], np.sign(d)], axis=1)
    pick = np.maximum.accumulate(np.where(np.c_[np.ones(n, bool), changed], cols, 0), axis=1)
    ways = np.take_along_axis(ways, pick, axis=1)
    continues = changed & (np.sign(d) == ways[:, :-1]) & (j - at[:, :-1] - 1.0 < RAMP_GAP)
    return Ramp(changed, continues, full[:, -1], ways[:, -1], m - 1.0 - at[:, -1])


def ramp_gated(now, period, ramp_t, ramp_from, since):
    """Whether the RL period ending at ``now`` (length ``period``) is not stepped for a
    setpoint ramp, vectorised (one clock): a change continued a ramp within it
    (``ramp_t``, the last that did; ``ramp_from``, the ramp's first change), and the ramp
    still runs (its last change was one of it, fewer than RAMP_GAP samples ago:
    ``since``, :func:`ramp_rule`'s) or ran RAMP_LONG RL periods. The agent learned from
    step responses: while a ramp runs a PI lags it by an error that grows as 1/ki, which
    it read as a sluggish loop. The engine (service.engine.rules) and training
    (service.learn.env) both decide with it."""
    running = (since < RAMP_GAP) & (ramp_t >= ramp_from)
    with np.errstate(invalid="ignore"):  # -inf - -inf: no ramp yet, none long
        long = ramp_t - ramp_from >= RAMP_LONG * period
    return (now - ramp_t < period) & (running | long)


class Moves(NamedTuple):
    """Per-loop state of the setpoint-move rule after one sample, arrays of shape (n,)."""

    moved: np.ndarray
    """The setpoint moved at this sample (bool)."""
    ref: np.ndarray
    """Setpoint at the last move (the reference the next move is measured from)."""
    anchor: np.ndarray
    """Setpoint before the first move of the current run of moves."""
    last_move: np.ndarray
    """Time of the last move (the caller's clock)."""
    gain: np.ndarray
    """Observation gain PAPER_MOVE / (size of the run of moves), within OBS_GAIN_RANGE."""


def track_moves(sp, ref, anchor, last_move, gain, now, step, run, scale=1.0) -> Moves:
    """One sample of the setpoint-move rule, vectorised over loops (arrays (n,) or scalars).

    A change of the setpoint ``sp`` from ``ref`` by at least ``step`` is a move (a NaN
    ``ref``, no setpoint seen yet, is none). A move in the same direction within ``run``
    of the previous one (same clock as ``now`` and ``last_move``) continues it: a ramp or
    a staircase is one move, measured from the setpoint before its first step
    (``anchor``), not a series of steps of ``step`` each, which would scale the error up
    4x. ``scale`` converts
    ``sp``'s units to agent units (``e_scale``). The engine calls it per sample
    (service.engine.rules), training per controller sample (service.learn.env)."""
    with np.errstate(invalid="ignore"):  # NaN references compare False
        moved = np.abs(sp - ref) >= step
        # a run continues in the same direction; a reversal starts a new one from its turn
        run_on = (now - last_move <= run) & (np.sign(sp - ref) == np.sign(ref - anchor))
    anchor = np.where(moved & ~run_on, ref, anchor)
    with np.errstate(divide="ignore"):
        size = np.abs(sp - anchor) * scale
        gain = np.where(moved, np.clip(PAPER_MOVE / size, *OBS_GAIN_RANGE), gain)
    ref = np.where(moved | np.isnan(ref), sp, ref)
    return Moves(moved, ref, anchor, np.where(moved, now, last_move), gain)


Factor = Annotated[float, Field(strict=True, ge=1e-9, le=1e9, allow_inf_nan=False)]
"""Every hint and factor lies within 1e-9..1e9, so derived gains stay finite and nonzero."""


class ScalingSpec(BaseModel):
    """How to map a loop into the agent's units: a model hint, overridable factor by factor."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    _resolved: Scaling = PrivateAttr()

    k_hat: Factor | None = Field(
        None,
        description="Rough process gain, output-to-PV, engineering units (its magnitude).",
    )
    tau_hat: Factor | None = Field(None, description="Rough process time constant, seconds.")
    pv_scale: Factor | None = Field(
        None,
        description="Typical error excursion in PV units (the paper's 10 cm); default 1.",
    )
    e_scale: Factor | None = Field(
        None,
        description="Override: agent error per engineering error (default 1/pv_scale).",
    )
    u_scale: Factor | None = Field(
        None,
        description="Override: agent controller output per engineering output "
        "(default e_scale * k_hat / 0.5).",
    )
    time_unit_s: Factor | None = Field(
        None,
        description="Override: seconds per agent time unit (default tau_hat / 0.5).",
    )

    @model_validator(mode="after")
    def _complete(self) -> ScalingSpec:
        if self.pv_scale is not None and self.e_scale is not None:
            raise ValueError("give pv_scale or e_scale, not both")
        if self.u_scale is None and self.k_hat is None:
            raise ValueError("need k_hat (model hint) or an explicit u_scale")
        if self.time_unit_s is None and self.tau_hat is None:
            raise ValueError("need tau_hat (model hint) or an explicit time_unit_s")
        e_scale = self.e_scale or 1.0 / (self.pv_scale or 1.0)
        u_scale = self.u_scale or e_scale * self.k_hat / AGENT_GAIN
        time_unit_s = self.time_unit_s or self.tau_hat / AGENT_TAU
        try:
            self._resolved = Scaling(e_scale=e_scale, u_scale=u_scale, time_unit_s=time_unit_s)
        except ValidationError as exc:
            msg = exc.errors()[0]["msg"]
            raise ValueError(f"derived scaling factor out of range: {msg}") from None
        return self

    @field_validator("k_hat", mode="before")
    @classmethod
    def _k_magnitude(cls, value: object) -> object:
        if isinstance(value, int | float) and not isinstance(value, bool) and value < 0:
            raise ValueError(
                "k_hat is the magnitude of the process gain: a process whose PV falls as "
                "the output rises is registered with k_hat > 0 and action 'direct' (the "
                "DCS block's controller action)"
            )
        return value

    def resolve(self) -> Scaling:
        """The factors, derived once, when the spec is validated."""
        return self._resolved


class Scaling(BaseModel):
    """Resolved factors between engineering and agent units (see the module docstring)."""

    model_config = ConfigDict(frozen=True)

    e_scale: Factor
    u_scale: Factor
    time_unit_s: Factor

    @property
    def kp_per_agent(self) -> float:
        """Engineering kp per agent kp."""
        return self.e_scale / self.u_scale

    @property
    def ki_per_agent(self) -> float:
        """Engineering ki (per second) per agent ki."""
        return self.e_scale / (self.u_scale * self.time_unit_s)

    @property
    def int_scale(self) -> float:
        """Agent error integral per engineering error integral (per second)."""
        return self.e_scale / self.time_unit_s

    @property
    def rl_period_s(self) -> float:
        """Plant seconds between two RL steps."""
        return RL_STEP_AGENT_UNITS * self.time_unit_s

    def apparent_gain(self, k: float) -> float:
        """Gain at which a plant of engineering gain ``k`` appears to the agent."""
        return k * self.e_scale / self.u_scale

    def apparent_tau(self, tau_s: float) -> float:
        """Time constant (agent units) at which a plant time constant in seconds appears."""
        return tau_s / self.time_unit_s

    def to_agent(self, kp: float, ki: float) -> tuple[float, float]:
        """Engineering (kp, ki per second) -> agent (kp, ki)."""
        return kp / self.kp_per_agent, ki / self.ki_per_agent

    def to_engineering(self, kp: float, ki: float) -> tuple[float, float]:
        """Agent (kp, ki) -> engineering (kp, ki per second)."""
        return kp * self.kp_per_agent, ki * self.ki_per_agent
