"""Integrating processes (levels, many temperatures): does the shipped agent tune them?
``pitune evaluate --integrating`` (issue 13: "tuning them is a later issue unless the
agent handles them well (measure it)").

The plants are integrators with dead time, ``k' / s e^{-theta s}``, seen through the
robustness suite's hint (:data:`service.learn.robust.HINT`) with a slope ``k'`` of
{0.5, 1, 2} per time unit (the box's FOPTD plants start at slopes K/tau of 0.25-4) and
a dead time of {0.05, 0.25, 0.5} time units, simulated as a first-order lag of
:data:`LAG` time units and gain ``k' LAG`` (a leak of 0.2 % over the run). Each runs
through the engine (:func:`service.learn.robust.run_condition`) for 80 RL periods from
the paper's kp = ki = 0.05:

- **the agent** (``guard.identify`` off: a user who trusts the hint and turned the check
  off) under the paper's protocol, noise 0.05 and load steps of 0.5. The final gains
  are scored by the paper's step test with the target closed-loop time constant
  :data:`TAU_CL` (twice the hint's apparent tau, as for the box's centre plant: an
  integrator has no tau of its own), beside SIMC for integrating processes at the same
  closed-loop time constant (Skogestad 2003: ``Kc = 1 / (k' (tau_c + theta))``,
  ``tau_I = 4 (tau_c + theta)``: :func:`plant_sim.tunings.simc` with the lag's tau).
- **the default guard** (the hint checked by identification): the RL period at which
  identification pauses the loop as integrating (status ``out_of_envelope``, audit
  ``out_of_envelope`` with ``"integrating": true``) and the step-test MSE of the gains it
  keeps.
"""

from __future__ import annotations

import json

import numpy as np

from plant_sim.tunings import simc, to_parallel
from service.learn.closed_loop import Policy
from service.learn.robust import HINT, Condition, Run, run_condition, score
from service.units import RL_STEP_AGENT_UNITS, ScalingSpec

LAG = 1e5
"""Time constant (time units) of the lag that stands for the integrator."""
TAU_CL = 1.0
"""The step test's target closed-loop time constant (time units)."""
SLOPES = (0.5, 1.0, 2.0)
"""The integrators' slopes as the hint shows them (agent units per time unit)."""
THETAS = (0.05, 0.25, 0.5)
"""Their dead times (time units)."""
CONDITIONS = (
    Condition("paper protocol"),
    Condition("noise 0.05", noise=0.05),
    Condition("load steps 0.5 every 7", load_step=0.5),
)
"""The robustness suite's conditions the agent runs under (the first: the check's run)."""
AGENT_ALONE = {"identify": False}
"""The guard of the agent's runs: no check of the hint, so nothing pauses the agent."""
PERIOD_S = RL_STEP_AGENT_UNITS * ScalingSpec(**HINT).resolve().time_unit_s
"""One RL period of the loops, seconds of plant time."""


def plants() -> tuple[np.ndarray, np.ndarray]:
    """(slope, theta) of the 9 plants, time units."""
    slope, theta = np.meshgrid(SLOPES, THETAS, indexing="ij")
    return slope.ravel(), theta.ravel()


def scores(slope, theta, kp, ki) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(step-test MSE against the target of :data:`TAU_CL`, not-settled mask, unstable
    mask) of gains (agent units) on the integrators. Not settled: the output still more
    than 0.5 off the target in the last fifth of the step test (11 time units), as the
    robustness suite counts unstable loops (a PI with little gain on an integrator
    oscillates slowly: kp = ki = 0.2 at slope 1 is damped 0.22 with a period of 14 time
    units); unstable: :func:`phase_margin` not positive."""
    mse, unsettled = score(slope * LAG, np.full(slope.shape, LAG), theta, 0.0, kp, ki,
                           tau_cl=TAU_CL)  # fmt: skip
    return mse, unsettled, ~(phase_margin(slope, theta, kp, ki) > 0.0)


def phase_margin(slope, theta, kp, ki) -> np.ndarray:
    """Phase margin (rad) of the PI ``kp + ki/s`` on ``slope/s e^(-theta s)``, arrays.
    The loop ``L = slope (kp s + ki) e^(-theta s) / s^2`` has a magnitude falling with
    frequency, so one crossover, where ``slope^2 (kp^2 w^2 + ki^2) = w^4``, and a phase
    of ``-pi + atan(kp w / ki) - w theta``: the closed loop is stable if and only if the
    margin there is positive (Nyquist: L starts at -pi from the double integrator)."""
    slope, theta, kp, ki = (np.asarray(v, np.float64) for v in (slope, theta, kp, ki))
    a = (slope * kp) ** 2
    w = np.sqrt((a + np.sqrt(a**2 + 4.0 * (slope * ki) ** 2)) / 2.0)
    return np.arctan2(kp * w, ki) - w * theta


def simc_gains(slope, theta) -> tuple[np.ndarray, np.ndarray]:
    """SIMC for integrating processes at tau_c = :data:`TAU_CL` (kp, ki; agent units)."""
    return to_parallel(*simc(slope * LAG, LAG, theta, TAU_CL))


def run(policy: Policy, cond: Condition, guard: dict | None, periods: int = 80) -> Run:
    """The nine integrators under ``cond`` through the engine (``guard``: as
    :func:`~service.learn.robust.run_condition`'s; None the default, the hint checked)."""
    slope, theta = plants()
    return run_condition(
        policy, cond, periods=periods, guard=guard,
        plants=(slope * LAG, np.full(slope.shape, LAG), theta / LAG),
    )  # fmt: skip


def integrating(policy: Policy, periods: int = 80) -> dict:
    """Both measurements (module doc); per-plant rows and a summary per condition."""
    slope, theta = plants()
    simc_mse, _, _ = scores(slope, theta, *simc_gains(slope, theta))
    out = {"periods": periods, "plants": {"slope": slope.tolist(), "theta": theta.tolist()},
           "simc_mse": simc_mse.tolist(), "agent": [], "checked": None}  # fmt: skip
    for cond in CONDITIONS:
        done = run(policy, cond, AGENT_ALONE, periods)
        kp, ki = done.gains[-1].T
        mse, unsettled, unstable = scores(slope, theta, kp, ki)
        out["agent"].append(
            {"condition": cond.name, "kp": kp.tolist(), "ki": ki.tolist(), "mse": mse.tolist(),
             "ratio_to_simc": (mse / simc_mse).tolist(), "not_settled": int(unsettled.sum()),
             "unstable": int(unstable.sum())}
        )  # fmt: skip
    out["checked"] = checked(run(policy, CONDITIONS[0], None, periods), slope, theta)
    return _finite(out)


def _finite(value):
    """``value`` with non-finite floats (an unstable loop's score) as None: valid JSON."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return None if isinstance(value, float) and not np.isfinite(value) else value


def checked(done, slope, theta) -> dict:
    """The default guard's run: per loop the plant time (s) and RL period of its first
    integrating pause (None: not paused), its status and the step-test MSE of its final
    gains. Drains the engine's audit rows."""
    engine = done.engine
    _, audit = engine.drain_changes()
    paused_at: list[float | None] = [None] * slope.size
    for row in audit:  # the first integrating pause of each loop
        loop, t, reason, detail = row[0], row[2], row[5], row[10]
        i = int(loop[1:])
        first = paused_at[i] is None and reason == "out_of_envelope"
        if first and json.loads(detail).get("integrating"):
            paused_at[i] = float(t)
    kp, ki = done.gains[-1].T
    mse, unsettled, unstable = scores(slope, theta, kp, ki)
    wall = float(done.t[-1])
    statuses = [engine.view(f"P{i}", wall=wall).status.value for i in range(slope.size)]
    at_period = [None if t is None else round(t / PERIOD_S, 1) for t in paused_at]
    return {"paused_at_s": paused_at, "paused_at_period": at_period, "status": statuses,
            "kp": kp.tolist(),
            "ki": ki.tolist(), "mse": mse.tolist(), "not_settled": int(unsettled.sum()),
            "unstable": int(unstable.sum())}  # fmt: skip


def _scores(values: list) -> np.ndarray:
    """Scores from the JSON: None (an unstable loop's) back to inf."""
    return np.array([np.inf if v is None else v for v in values], np.float64)


def render(result: dict) -> str:
    """integrating.md: the agent's table and the check's, per plant."""
    slope, theta = (np.array(result["plants"][k]) for k in ("slope", "theta"))
    simc_mse = _scores(result["simc_mse"])
    lines = [
        "# pitune on integrating processes (through the tuning engine)",
        "",
        f"9 integrators k'/s e^(-theta s) (slope k' {', '.join(map(str, SLOPES))} per time"
        f" unit x dead time {', '.join(map(str, THETAS))} time units, as the robustness"
        f" suite's hint shows them), {result['periods']} RL periods from kp = ki = 0.05."
        f" Step-test MSE of the final gains against the target exp(-theta s)/({TAU_CL:g} s"
        " + 1); SIMC for integrating processes at the same closed-loop time constant"
        f" scores {simc_mse.min():.3g}-{simc_mse.max():.3g}.",
        "",
        "The agent alone (`guard.identify` off):",
        "",
        "| condition | worst MSE | median MSE | worst / median ratio to SIMC | beats SIMC |"
        " not settled in the step test | unstable |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in result["agent"]:
        mse, ratio = _scores(r["mse"]), _scores(r["ratio_to_simc"])
        lines.append(
            f"| {r['condition']} | {mse.max():.3g} | {np.median(mse):.3g} |"
            f" {ratio.max():.1f}x / {np.median(ratio):.1f}x |"
            f" {np.mean(ratio < 1.0) * 100:.0f}% | {r['not_settled']} | {r['unstable']} |"
        )
    c = result["checked"]
    kept = _scores(c["mse"])
    paused = [p for p in c["paused_at_period"] if p is not None]
    lines += [
        "",
        "Default guard (the hint checked by identification), paper protocol: "
        f"{len(paused)} of {slope.size} loops paused as integrating"
        + (f", at RL period {min(paused):g}-{max(paused):g}" if paused else "")
        + f"; final worst / median MSE {kept.max():.3g} / {np.median(kept):.3g}"
        f" (the gains the pause kept), not settled in the step test {c['not_settled']},"
        f" unstable {c['unstable']}.",
        "",
        "| slope | theta | SIMC MSE | agent MSE (paper protocol) | paused at RL period | status |",
        "|---|---|---|---|---|---|",
    ]
    agent = _scores(result["agent"][0]["mse"])
    for i in range(slope.size):
        at = c["paused_at_period"][i]
        lines.append(
            f"| {slope[i]:g} | {theta[i]:g} | {simc_mse[i]:.3g} | {agent[i]:.3g} |"
            f" {'-' if at is None else f'{at:g}'} | {c['status'][i]} |"
        )
    return "\n".join(lines) + "\n"
