"""``pitune verify-eval``: how often verify-or-rollback is right, on simulated loops driven
through the tuning engine.

N FOPTD loops (K 0.5-2, tau 5-20 s, theta 0.1-0.5 tau, hinted exactly, pv_scale 1) run
under PI control, sampled every second with white measurement noise (``--noise``, share
of the setpoint move; the issue's 2 %), the setpoint toggling between 0 and 1 every 4 RL
periods (the paper's schedule). The agent is replaced by one that never moves (so every
change is the one under test). The loops start at SIMC gains (Skogestad 2003) of a slow
closed-loop time constant; after two setpoint responses (the baseline) an operator
changes the gains in the DCS (the gateway reports them: adopted), and two more responses
follow. The engine's verdict of that change is read from its audit log.

* ``good`` changes: SIMC gains of a faster or about equal time constant, kept when the
  noise-free IAE of the change is at most 1.05 times the old one: every rollback of
  one is a false rollback.
* ``bad`` changes: kp cut to 0.1-0.4 of well-tuned SIMC gains, ki left as it was (the
  integral time shortened), kept when the noise-free IAE at least doubles: every one
  must be rolled back within one verification window (the next complete setpoint
  response).
* ``detune`` changes: both gains cut by one factor of 0.2-0.6 (an operator's detune:
  :func:`service.engine.reported.is_detune`), kept when the noise-free IAE at least
  doubles: judged ``worse`` and kept, never rolled back automatically (docs/tuner.md,
  Verdicts), within the same window.
* ``oscillating`` changes: kp raised to 1.3 times the loop's ultimate gain (the loop
  goes unstable): must be rolled back on the oscillation detector, within 3 periods of
  the oscillation (``verdict_after_periods``: setpoint periods for the other kinds),
  counted from its emergence (the noise-free error out of the 3-sigma band at least once
  a period from then on) and, in ``from_first_exceedance``, from the first time the
  noise-free error left the band at all (the amplified noise may do that first). The
  period is the oscillation's own (``true_period``: :func:`oscillation_period`, the
  noise-free loop with the new gains) and, as first reported, the detector's estimate
  (its last two half-periods between zero crossings).
* ``aggressive`` changes (``--aggressive``, 300 loops of the oscillating kind's plants
  and old ki, kp 0.5, 0.6 and 0.7 Ku): stable loops tuned hard; the loops the
  oscillation detector flags at any time are false alarms, or lightly damped loops at
  the line (the report lists how many).

Prints the verdict counts per kind and writes JSON with ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import orjson

from plant_sim.foptd import FOPTDBatch
from plant_sim.loop import step_test
from plant_sim.pi import PIBatch
from service.engine import LoopConfig, TuningEngine
from service.engine.config import Guard
from service.units import RL_STEP_AGENT_UNITS

DT = 1.0
"""Sample period of every simulated loop, s."""
KINDS = ("good", "bad", "oscillating", "detune")
"""The kinds of change, drawn in this order from one stream (a kind added goes last: the
draws of those before it stay as reported)."""
MARGIN = Guard.model_fields["verify_margin"].default
"""The loops' ``verify_margin``: the default unless ``--margin``."""
U_LIMIT = 10.0
"""Controller output limits (the steady state needs at most 2): an unstable loop's
oscillation saturates into a limit cycle, as on a plant."""


class StillAgent:
    """An agent that never changes the gains (zero steps), with a one-number state."""

    class cfg:  # noqa: N801 - the attribute the engine reads, as on the real agent
        layers = 1
        hidden = 1

    def act(self, obs: np.ndarray, state: np.ndarray, forgetting) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros((len(obs), 2)), state


def simc(K, tau, theta, lam) -> tuple[np.ndarray, np.ndarray]:
    """SIMC PI gains (kp, ki per s) for closed-loop time constant ``lam``."""
    kp = tau / (K * (lam + theta))
    return kp, kp / np.minimum(tau, 4.0 * (lam + theta))


def true_iae(K, tau, theta, gains: np.ndarray, horizon: np.ndarray) -> np.ndarray:
    """Noise-free IAE per unit move over each loop's judging window (2 RL periods)."""
    dt = DT  # the simulation's own discretisation (a sampled PI adds half a sample of lag)
    span = float(horizon.max())
    trace = step_test(K, tau, theta, gains[:, 0], gains[:, 1], dt=dt, horizon=span)
    steps = np.arange(trace.e.shape[1]) * dt
    inside = steps[None, :] <= horizon[:, None]
    return (np.abs(trace.e) * inside).sum(axis=1) * dt / 2.0


def scenario(kind: str, n: int, rng: np.random.Generator) -> dict:
    """Plants, gains before and after the change (each (n,) or (n, 2))."""
    K, tau = rng.uniform(0.5, 2.0, 4 * n), rng.uniform(5.0, 20.0, 4 * n)
    theta = tau * rng.uniform(0.1, 0.5, 4 * n)
    horizon = 2.0 * RL_STEP_AGENT_UNITS * 2.0 * tau  # RL period = 5.5 tau (hint exact)
    if kind == "good":
        lam_old = theta * rng.uniform(1.5, 4.0, 4 * n)
        lam_new = np.where(rng.random(4 * n) < 0.5, theta * rng.uniform(1.0, 1.5, 4 * n),
                           lam_old * rng.uniform(0.9, 1.1, 4 * n))  # fmt: skip
        old, new = (
            np.column_stack(simc(K, tau, theta, lam_old)),
            np.column_stack(simc(K, tau, theta, lam_new)),
        )
    elif kind in ("bad", "detune"):
        old = np.column_stack(simc(K, tau, theta, theta * rng.uniform(1.0, 2.0, 4 * n)))
        if kind == "bad":
            new = old * np.column_stack([rng.uniform(0.1, 0.4, 4 * n), np.ones(4 * n)])
        else:
            new = old * rng.uniform(0.2, 0.6, (4 * n, 1))
    else:
        old = np.column_stack(simc(K, tau, theta, theta * rng.uniform(1.0, 2.0, 4 * n)))
        ku, period = ultimate(K, tau, theta)
        new = np.column_stack([1.3 * ku, old[:, 1]])
    ratio = true_iae(K, tau, theta, new, horizon) / true_iae(K, tau, theta, old, horizon)
    keep = {
        "good": np.flatnonzero(ratio <= 1.05), "bad": np.flatnonzero(ratio >= 2.0),
        "detune": np.flatnonzero(ratio >= 2.0), "oscillating": np.arange(4 * n),
    }[kind][:n]  # fmt: skip
    out = {"K": K[keep], "tau": tau[keep], "theta": theta[keep], "old": old[keep],
           "new": new[keep], "ratio": ratio[keep]}  # fmt: skip
    if kind == "oscillating":
        out["period"] = ultimate(out["K"], out["tau"], out["theta"])[1]
    return out


def ultimate(K, tau, theta) -> tuple[np.ndarray, np.ndarray]:
    """Ultimate gain and period of FOPTD loops under P control (phase -180 degrees at
    w: theta w + atan(tau w) = pi, solved by bisection)."""
    lo, hi = np.zeros_like(tau), np.pi / theta
    for _ in range(60):
        w = 0.5 * (lo + hi)
        over = theta * w + np.arctan(tau * w) > np.pi
        hi, lo = np.where(over, w, hi), np.where(over, lo, w)
    w = 0.5 * (lo + hi)
    return np.sqrt(1.0 + (tau * w) ** 2) / K, 2.0 * np.pi / w


def oscillation_period(K, tau, theta, gains: np.ndarray, span: float) -> np.ndarray:
    """The period of the oscillation of each (unstable) loop with ``gains``, s: twice the
    mean interval between the 2nd and 9th zero crossings of the error in a noise-free
    step test of the same sampled loop (crossing times interpolated; NaN: too few)."""
    e = step_test(K, tau, theta, gains[:, 0], gains[:, 1], dt=DT, horizon=span).e
    out = np.full(len(e), np.nan)
    for i, x in enumerate(e):
        ok = np.isfinite(x[:-1]) & np.isfinite(x[1:]) & (x[:-1] != 0.0)
        at = np.flatnonzero(ok & (np.sign(x[:-1]) != np.sign(x[1:])))
        crossings = at + x[at] / (x[at] - x[at + 1])
        if crossings.size >= 3:
            out[i] = 2.0 * DT * float(np.diff(crossings[1:9]).mean())
    return out


def run_scenario(
    sc: dict,
    *,
    noise: float,
    mode: str = "auto",
    seed: int = 0,
    margin: float = MARGIN,
    monitoring: bool = True,
) -> dict:
    """Drive the engine through one scenario; returns the verdict of each loop's change
    ('verified', 'rolled_back', 'rollback_proposed', 'worse', 'pending') and when it came
    (``monitoring``: the engine's switch, see :class:`TuningEngine`)."""
    K, tau, theta, old, new = sc["K"], sc["tau"], sc["theta"], sc["old"], sc["new"]
    n = K.size
    rng = np.random.default_rng(seed)
    engine = TuningEngine(StillAgent(), monitoring=monitoring)
    ids = [f"L{i}" for i in range(n)]
    for i in range(n):
        engine.register(LoopConfig(
            id=ids[i], kp=float(old[i, 0]), ki=float(old[i, 1]), sample_period_s=DT, mode=mode,
            scaling={"k_hat": float(K[i]), "tau_hat": float(tau[i]), "pv_scale": 1.0},
            # verification alone: identification (on for hinted loops by default) would
            # put the first confident model's tuning in force, a second change in the
            # window judged (model_check.hint_checked)
            guard={"excitation_periods": 0.0, "verify_margin": margin, "identify": False},
        ), wall=0.0)  # fmt: skip
    rl = RL_STEP_AGENT_UNITS * 2.0 * tau
    toggle = np.rint(4.0 * rl / DT).astype(np.int64)
    change_at = 2 * toggle + toggle // 4  # a quarter into the third response
    end = int((4 * toggle).max()) + 2
    plant = FOPTDBatch(K, tau, theta, dt=DT, max_theta=float(theta.max()) + DT)
    plant.reset(0.0)
    pi = PIBatch(old[:, 0].copy(), old[:, 1].copy(), dt=DT, n=n, u_min=-U_LIMIT, u_max=U_LIMIT)
    pi.initialise(np.zeros(n))
    slot = {loop_id: i for i, loop_id in enumerate(ids)}
    changed = np.zeros(n, bool)
    band = 3.0 * noise  # the detector's band once its noise estimate has settled
    # after the change, until the engine answers it: the first time the noise-free error
    # leaves the band, and the start of the run of such times that leaves no gap of a
    # whole oscillation period (the oscillation has emerged from the noise for good)
    onset = np.full(n, np.nan)
    emerged, last_out = np.full(n, np.nan), np.full(n, -np.inf)
    period = sc.get("period", np.full(n, np.inf))
    answered = np.zeros(n, bool)
    flagged = np.zeros(n, bool)  # the oscillation detector's flag, at any time
    slots = np.array([engine.table.slot(i) for i in ids])
    for k in range(end):
        t = k * DT
        sp = ((k // toggle) % 2).astype(np.float64)
        y = plant.output()
        pv = y + noise * rng.standard_normal(n)
        out = changed & ~answered & (np.abs(sp - y) > band)
        onset = np.where(np.isnan(onset) & out, t, onset)
        emerged = np.where(out & (t - last_out > period), t, emerged)
        last_out = np.where(out, t, last_out)
        now = k == change_at
        if now.any():
            pi.set_gains(np.where(now, new[:, 0], pi.kp), np.where(now, new[:, 1], pi.ki))
            changed |= now
        samples = [
            {"loop_id": ids[i], "t": t, "sp": float(sp[i]), "pv": float(pv[i]),
             "kp": float(pi.kp[i]), "ki": float(pi.ki[i])}
            for i in range(n)
        ]  # fmt: skip
        for u in engine.ingest(samples, wall=float(t)):
            i = slot[u.loop_id]
            answered[i] |= u.reason == "rollback"
            if u.mode == "auto":  # the gateway applies auto updates
                kp, ki = pi.kp.copy(), pi.ki.copy()
                kp[i], ki[i] = u.kp, u.ki
                pi.set_gains(kp, ki)
        # the period is measured when the detector flags (a rollback forgets the flag)
        flagged |= np.isfinite(engine.table.o_per[slots])
        plant.step(pi.step(sp - pv))
    if "period" in sc:  # oscillation periods from the oscillation's onset
        at = change_at * DT
        out = _verdicts(
            engine, ids, np.where(np.isnan(emerged), at, emerged), sc["period"],
            first=np.where(np.isnan(onset), at, onset),
        )  # fmt: skip
    else:
        out = _verdicts(engine, ids, change_at * DT, toggle * DT)
    out["flagged"] = flagged.tolist()
    return out


def _verdicts(engine: TuningEngine, ids: list[str], since, unit: np.ndarray, first=None) -> dict:
    """Each loop's verdict of its change, from the audit rows the engine produced, and
    when it came in ``unit`` from ``since`` (and from ``first``, if given)."""
    _, audit = engine.drain_changes()
    slot = {loop_id: i for i, loop_id in enumerate(ids)}
    verdict = ["pending"] * len(ids)
    at, at_first = [math.nan] * len(ids), [math.nan] * len(ids)
    start = since if first is None else first
    details: list[dict | None] = [None] * len(ids)
    for row in audit:
        i = slot[row[0]]
        if row[5] not in ("verified", "rollback", "verdict") or verdict[i] != "pending":
            continue
        if row[2] is None or row[2] < start[i] - 1e-9:
            continue  # the baseline
        detail = details[i] = json.loads(row[10])
        verdict[i] = detail["verdict"]
        # an oscillation's own period, as the detector measured it
        per = detail.get("period_s") or unit[i]
        at[i] = float((row[2] - since[i]) / per)
        if first is not None:
            at_first[i] = float((row[2] - first[i]) / per)
    out = {"verdict": verdict, "after_periods": at, "detail": details}
    if first is not None:
        out["after_periods_first"] = at_first
    return out


def _timing(after: list[float]) -> dict:
    done = [float(a) for a in after if math.isfinite(a)]
    return {
        "verdict_after_periods_max": max(done) if done else None,
        "verdict_after_periods_median": float(np.median(done)) if done else None,
        "verdict_within_3_periods": sum(a <= 3.0 for a in done) / max(len(after), 1),
    }


def _counts(values: list[str]) -> dict[str, int]:
    counts: dict[str, int] = {}
    for v in values:
        counts[v] = counts.get(v, 0) + 1
    return counts


def evaluate(
    n: int, noise: float, seed: int = 0, margin: float = MARGIN, aggressive: bool = False
) -> dict:
    rng = np.random.default_rng(seed)
    report: dict = {"loops": n, "noise": noise, "margin": margin}
    for kind in KINDS:
        sc = scenario(kind, n, rng)
        out = run_scenario(sc, noise=noise, seed=seed, margin=margin)
        report[kind] = {
            "changes": int(sc["K"].size),
            "verdicts": _counts(out["verdict"]),
            "true_iae_ratio_median": float(np.median(sc["ratio"])),
            **_timing(out["after_periods"]),
        }
        if "after_periods_first" in out:
            # the detector's period estimate as the unit (above), the oscillation's own
            # (true_period), and the stricter clock (noise may start it early)
            est = np.array([(d or {}).get("period_s") or np.nan for d in out["detail"]])
            true = oscillation_period(sc["K"], sc["tau"], sc["theta"], sc["new"],
                                      12.0 * float(sc["period"].max()))  # fmt: skip
            scale = est / true
            report[kind]["true_period"] = _timing(list(np.array(out["after_periods"]) * scale))
            report[kind]["from_first_exceedance"] = _timing(out["after_periods_first"])
    if aggressive:
        report["aggressive"] = evaluate_aggressive(min(n, 300), noise, seed + 1, margin)
    good = report["good"]
    report["false_rollback_rate"] = good["verdicts"].get("rolled_back", 0) / good["changes"]
    return report


def evaluate_aggressive(n: int, noise: float, seed: int, margin: float = MARGIN) -> dict:
    """Stable loops tuned hard (kp 0.5, 0.6, 0.7 Ku): how many the oscillation detector
    flags at any time, and the verdicts of the changes."""
    base = scenario("oscillating", n, np.random.default_rng(seed))
    ku, _ = ultimate(base["K"], base["tau"], base["theta"])
    out = {}
    for share in (0.5, 0.6, 0.7):
        sc = {k: v for k, v in base.items() if k != "period"}
        sc["new"] = np.column_stack([share * ku, base["old"][:, 1]])
        res = run_scenario(sc, noise=noise, seed=seed, margin=margin)
        why = [(d or {}).get("why") for d in res["detail"]]
        out[f"{share:g}_ku"] = {
            "changes": n,
            "flagged_oscillating": int(sum(res["flagged"])),
            "rolled_back_on_oscillation": why.count("oscillation"),
            "verdicts": _counts(res["verdict"]),
        }
    return out


def _count(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text}: at least 1")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--loops", type=_count, default=1000, help="changes per kind")
    parser.add_argument("--noise", type=float, default=0.02, help="noise sigma, share of the move")
    parser.add_argument("--seed", type=int, default=0, help="random seed")
    parser.add_argument("--margin", type=float, default=MARGIN, help="the loops' verify_margin")
    parser.add_argument(
        "--aggressive", action="store_true", help="also stable loops at kp 0.5-0.7 Ku"
    )
    parser.add_argument("--out", type=Path, default=None, help="write the report as JSON here")


def run(args: argparse.Namespace) -> int:
    report = evaluate(args.loops, args.noise, args.seed, args.margin, args.aggressive)
    text = orjson.dumps(report, option=orjson.OPT_INDENT_2).decode()
    print(text)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")
    return 0
