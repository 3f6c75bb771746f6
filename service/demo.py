"""``pitune demo``: the tuner and a simulated two-tank plant, end to end, on loopback.

Starts the tuner daemon (admin API and Zenoh peer on free loopback ports, SQLite in a
work folder) and the plant simulator as separate processes; the plant registers the
two-tank level loop with the paper's crude model 1.2/(30 s + 1) and runs a fixed
simulated span at a high speed factor while a progress line shows the simulated time,
the gains in force and the recent tracking error. Both processes are then stopped and
``demo/`` receives:

* ``two_tank.png``: level vs setpoint vs target, tuned and untuned, and kp, ki over time;
* ``summary.md`` and ``summary.json``: the tracking MSE (the level without its
  measurement noise vs the target trajectory, over the last two setpoint changes:
  :meth:`plant_sim.trajectory.Trajectory.tracking_mse`) of the tuned run and of the
  untuned baseline;
* ``tank1.csv``: the tuned run's trajectory log.

The untuned baseline is the same plant, schedule and seed simulated in-process with
the registered gains held fixed (:func:`plant_sim.config.untuned_baseline`). The
processes run in a :class:`service.procs.Stack`.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

from plant_sim.config import SP_PERIOD_S, LoopSpec, Simulation, untuned_baseline
from plant_sim.process import plant_argv, seed
from plant_sim.scenario import TANK_FIT, TANK_HINT
from plant_sim.trajectory import plot, read_log
from plant_sim.tunings import simc_improved, to_parallel
from service.procs import STORE_NAME, Proc, ProcError, Stack, user_path, weights_path

LOOP = LoopSpec("two_tank", "tank1")
LOOP_ID = LOOP.loop_id
MSE_CHANGES = 2
"""The tracking MSE covers the last two setpoint changes, when tuning has settled."""

TUNER_LAG_S = 5.0
"""Simulated seconds the plant may run ahead of the tuner (``pitune plant run
--tuner-lag``): the demo's result then does not depend on whether the machine keeps up
with ``--speed`` (a tenth of the tank's time constant, a fiftieth of an RL period)."""


class DemoError(RuntimeError):
    """The run went wrong although its processes did not fail; the message says how."""


# -- the demo ----------------------------------------------------------------------------
MIN_MINUTES = MSE_CHANGES * SP_PERIOD_S / 60.0 + 1.0
"""Shortest run that has the setpoint changes the tracking MSE covers (every 10 min)."""


MAX_MINUTES = 1e6
"""Longest run (about two simulated years): the plant must be told a finite duration, and
``inf`` passed this check to fail later with the plant subcommand's usage error."""


def _minutes(text: str) -> float:
    value = float(text)
    if not value >= MIN_MINUTES:
        raise argparse.ArgumentTypeError(
            f"{text}: at least {MIN_MINUTES:g} minutes (the tracking MSE covers the last "
            f"{MSE_CHANGES} setpoint changes, one every {SP_PERIOD_S / 60:g} minutes)"
        )
    if not value <= MAX_MINUTES:
        raise argparse.ArgumentTypeError(f"{text}: at most {MAX_MINUTES:g} minutes")
    return value


def _speed(text: str) -> float:
    value = float(text)
    if not 0.0 < value <= 10_000.0:
        raise argparse.ArgumentTypeError(f"{text}: a speed factor in (0, 10000]")
    return value


def _noise(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 10.0:
        raise argparse.ArgumentTypeError(f"{text}: noise amplitude in [0, 10] cm")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("demo"), help="output folder (demo/)")
    parser.add_argument(
        "--minutes",
        type=_minutes,
        default=60.0,
        help=f"simulated span, minutes, {MIN_MINUTES:g} to {MAX_MINUTES:g} (60)",
    )
    parser.add_argument(
        "--speed", type=_speed, default=60.0, help="simulated seconds per wall second (60)"
    )
    parser.add_argument(
        "--noise",
        type=_noise,
        default=0.0,
        help="level measurement noise +-N cm (0; the paper's noisy run uses 1)",
    )
    parser.add_argument("--seed", type=seed, default=0)
    parser.add_argument(
        "--workdir",
        type=user_path,
        default=None,
        help="keep the database and logs here (default: temp); a folder without a previous "
        f"run's {STORE_NAME}: each run starts from the registered gains, as its untuned "
        "baseline does",
    )
    parser.add_argument(
        "--agent-weights", type=weights_path, default=None, metavar="FILE", help="for the tuner"
    )
    parser.add_argument(
        "--no-hint",
        action="store_true",
        help="register the loop without a model hint: the tuner identifies the model from "
        "the closed-loop data first (docs/identification.md)",
    )
    parser.add_argument(
        "--keep",
        action="store_true",
        help="after the run, leave the tuner and its console up until Ctrl-C or SIGTERM",
    )


def _ended(signum: int, frame) -> None:
    raise SystemExit(128 + signum)


def usage_error(args: argparse.Namespace) -> str | None:
    """Why the run cannot start or could not write its report (None: it can), checked
    before any process starts, not after minutes of running."""
    out = args.out
    if out.exists() and not out.is_dir():
        return f"--out {out} is a file: give a folder for the report"
    folder = next(p for p in (out.absolute(), *out.absolute().parents) if p.exists())
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        return f"--out {out}: cannot write into {folder}"
    if args.workdir is not None and (args.workdir / STORE_NAME).exists():
        # the tuner would resume the previous run's loop, tuned already, and the summary
        # compare that with an untuned baseline: not the demo's comparison
        return (
            f"--workdir {args.workdir} holds a previous run's {STORE_NAME}: give a new "
            "folder, or remove it for a fresh run"
        )
    return None


def run(args: argparse.Namespace) -> int:
    started = time.monotonic()
    if problem := usage_error(args):
        print(f"pitune demo: {problem}", file=sys.stderr)
        return 2
    # A terminal closed or a `kill` ends the demo as Ctrl-C does: through the stack's
    # teardown (tuner and plant stopped, the temporary folder removed), never leaving a
    # tuner behind on its ports
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, _ended)
    try:
        with contextlib.ExitStack() as stack:
            workdir = args.workdir or Path(stack.enter_context(tempfile.TemporaryDirectory()))
            Demo(args, workdir).run(started)
    except (ProcError, DemoError) as exc:
        print(f"\npitune demo failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # Ctrl-C: the stack stopped its processes on the way out
        print("\npitune demo: interrupted", file=sys.stderr)
        return 130
    return 0


class Demo:
    """One demo run: the stack, the loop's progress while it runs, and the report."""

    def __init__(self, args: argparse.Namespace, workdir: Path) -> None:
        self.args = args
        self.workdir = workdir
        self.duration_s = args.minutes * 60.0
        # The plant process and the in-process baseline simulate this (the pace is the
        # stack's --speed: it does not change the simulated trajectory).
        self.sim = Simulation(duration=self.duration_s, noise=args.noise, seed=args.seed)

    def run(self, started: float) -> None:
        """Run the stack, follow the loop, write the report (``started``: monotonic time
        of the command, for the wall time in the report)."""
        with Stack(
            self.workdir, speed=self.args.speed, agent_weights=self.args.agent_weights
        ) as st:
            print(f"starting the tuner (API {st.api}, Zenoh {st.zenoh}) ...", flush=True)
            tuner = st.start_tuner()
            # Reading the console needs no token; acting does (docs/console.md).
            print(f"operator console: {st.api}/ui (log in with the token {st.token})", flush=True)
            if self.args.no_hint:  # registered first: the plant's own registration resumes it
                self.register_without_hint(st.api, st.token)
            lag = ("--tuner-lag", f"{TUNER_LAG_S:g}")
            plant = st.start_plant(*plant_argv((LOOP,), self.sim), *lag)
            print(f"plant simulator started: {self.args.minutes:g} simulated minutes "
                  f"at {self.args.speed:g}x", flush=True)  # fmt: skip
            view = self.follow(st.api, plant, tuner)
            self.report(view, wall_s=time.monotonic() - started)
            if self.args.keep:
                keep_up(st.api, tuner)
            if tuner.stop() != 0:  # the tuner exits 0 after a graceful SIGTERM shutdown
                raise tuner.failed()

    def register_without_hint(self, api: str, token: str) -> None:
        body = LOOP.registration(self.sim.scan)
        del body["scaling"]
        deadline = time.monotonic() + 60.0
        auth = {"Authorization": f"Bearer {token}"}
        with httpx.Client(base_url=api, timeout=5.0, headers=auth) as client:
            while True:
                try:
                    response = client.post("/loops", json=body)
                    break
                except httpx.TransportError:
                    if time.monotonic() > deadline:
                        raise DemoError(f"tuner API at {api} unreachable") from None
                    time.sleep(0.2)
        if response.status_code != 201:
            raise DemoError(f"registering without a hint: HTTP {response.status_code}")

    def follow(self, api: str, plant: Proc, tuner: Proc) -> dict:
        """Show progress until the plant finishes its span; the loop's final view."""
        deadline = time.monotonic() + self.duration_s / self.args.speed + 90.0
        log = self.workdir / "log" / f"{LOOP_ID}.csv"
        progress = Progress(self.duration_s)
        view: dict = {}
        with httpx.Client(base_url=api, timeout=5.0) as client:
            while plant.running:
                if not tuner.running:
                    raise tuner.failed()
                if time.monotonic() > deadline:
                    raise DemoError(f"the run did not finish in time:\n{plant.tail()}")
                with contextlib.suppress(httpx.HTTPError):
                    response = client.get(f"/loops/{LOOP_ID}")
                    if response.is_success:
                        view = response.json()
                        progress.show(view, log)
                time.sleep(0.5)
            if plant.returncode != 0:
                raise plant.failed()
            view = client.get(f"/loops/{LOOP_ID}").json()
        progress.show(view, log, final=True)
        return view

    def report(self, view: dict, *, wall_s: float) -> dict:
        """Write the PNG, the summaries and the log to ``--out``; print the summary."""
        out = self.args.out
        out.mkdir(parents=True, exist_ok=True)
        log = self.workdir / "log" / f"{LOOP_ID}.csv"
        tuned = read_log(log)
        baseline = untuned_baseline((LOOP,), self.sim)[LOOP_ID]
        if len(tuned) != len(baseline):
            raise DemoError(f"the plant logged {len(tuned)} scans, expected {len(baseline)}")
        shutil.copyfile(log, out / f"{LOOP_ID}.csv")
        mse_tuned, mse_untuned = tuned.tracking_mse(MSE_CHANGES), baseline.tracking_mse(MSE_CHANGES)
        tau_c = 2 * TANK_FIT[1]
        simc_kp, simc_ki = (float(g) for g in to_parallel(*simc_improved(*TANK_FIT, tau_c)))
        summary = {
            "loop": LOOP_ID,
            "simulated_minutes": self.args.minutes,
            "speed": self.args.speed,
            "wall_s": round(wall_s, 1),
            "noise_cm": self.args.noise,
            "seed": self.args.seed,
            "mse_window_start_s": float(tuned.setpoint_changes()[-MSE_CHANGES]),
            "mse_tuned_cm2": mse_tuned,
            "mse_untuned_cm2": mse_untuned,
            "improvement": mse_untuned / mse_tuned,
            "registered_gains": {"kp": view["config"]["kp"], "ki": view["config"]["ki"]},
            "final_gains": {"kp": view["kp"], "ki": view["ki"]},
            "gain_updates": view["seq"],
            "simc_reference_gains": {"kp": simc_kp, "ki": simc_ki},
            "hint": None if self.args.no_hint else {"k": TANK_HINT[0], "tau_s": TANK_HINT[1]},
            "linearisation": dict(zip(("k", "tau_s", "theta_s"), TANK_FIT, strict=True)),
            "identified": _identified(view),
            "status": view.get("status"),
        }
        (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        (out / "summary.md").write_text(summary_markdown(summary))
        plot(
            {"tuned by pitune": tuned, "untuned (registered gains)": baseline},
            out / "two_tank.png",
            title=f"Two-tank level loop, {self.args.minutes:g} simulated minutes "
            f"(tracking MSE {mse_tuned:.3g} vs {mse_untuned:.3g} cm^2 untuned)",
            units="level, cm",
            gain_units="(L/min)/cm",
        )
        print(summary_markdown(summary), end="")
        print(f"wrote {out}/two_tank.png, summary.md, summary.json, {LOOP_ID}.csv")
        return summary


_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def keep_up(api: str, tuner: Proc) -> None:
    """Leave the tuner (and its console) running until Ctrl-C, SIGTERM or its own exit."""
    print(f"--keep: the tuner stays up, console at {api}/ui; Ctrl-C stops it", flush=True)
    stop = threading.Event()
    # SIGINT handled explicitly too: a demo started in the background inherits an ignored
    # SIGINT (shells do that), and Python then raises no KeyboardInterrupt
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in _STOP_SIGNALS}
    try:
        while tuner.running and not stop.wait(0.5):
            pass
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _identified(view: dict) -> dict | None:
    """The model identification put in force (or its latest, unconfident, one)."""
    ident = view.get("identification") or {}
    model = ident.get("in_force") or ident.get("model")
    if model is None:
        return {"why": ident.get("why", "")} if ident else None
    return {
        "k": model["k"], "tau_s": model["tau"], "theta_s": model["theta"],
        "confidence": model["confidence"], "in_force": ident.get("in_force") is not None,
        "why": ident.get("why", ""),
    }  # fmt: skip


def _model_lines(s: dict) -> str:
    lines = [
        "",
        "| model of the tank | K (cm per L/min) | tau (s) | theta (s) |",
        "|---|---|---|---|",
    ]
    # the crude model is shown either way: a hint-free run's identification is read beside it
    hint = s.get("hint") or {"k": TANK_HINT[0], "tau_s": TANK_HINT[1]}
    what = "the paper's crude hint" + ("" if s.get("hint") else " (not given to the tuner)")
    lines.append(f"| {what} | {hint['k']:g} | {hint['tau_s']:g} | - |")
    lin = s["linearisation"]
    lines.append(
        f"| linearisation around 55 cm | {lin['k']:g} | {lin['tau_s']:g} | {lin['theta_s']:g} |"
    )
    ident = s.get("identified")
    if ident and "k" in ident:
        what = "identified from the closed loop" + ("" if ident["in_force"] else " (not confident)")
        lines.append(
            f"| {what} | {ident['k']:.3g} | {ident['tau_s']:.3g} | {ident['theta_s']:.3g} |"
        )
    elif ident:
        lines.append(f"| not identified: {ident['why']} | - | - | - |")
    return "\n".join(lines) + "\n"


def _hint_line(s: dict) -> str:
    if s.get("hint") is None:
        return "No model hint: the tuner identified the loop (status " + str(s.get("status")) + ")."
    return "Model hint given to the tuner: 1.2 cm/(L/min), 30 s."


def _noise_note(s: dict) -> str:
    if not s["noise_cm"]:
        return ""
    return (
        f"The level as measured adds the noise's variance, {s['noise_cm'] ** 2 / 3:.3g} cm^2, "
        "to both (no tuning removes it).\n"
    )


def summary_markdown(s: dict) -> str:
    reg, fin, simc = s["registered_gains"], s["final_gains"], s["simc_reference_gains"]
    lin = s["linearisation"]
    return f"""# pitune demo: two-tank level loop

{s["simulated_minutes"]:g} simulated minutes at {s["speed"]:g}x real time ({s["wall_s"]:g} s wall),
level setpoint stepping between 50 and 60 cm every 10 minutes, measurement noise
+-{s["noise_cm"]:g} cm, seed {s["seed"]}. {_hint_line(s)}
{_model_lines(s)}
Tracking MSE, the level without its measurement noise vs the target trajectory
exp(-15 s)/(94 s + 1) applied to the setpoint, over the last {MSE_CHANGES} setpoint changes
(t >= {s["mse_window_start_s"]:g} s):

| run | kp, L/min/cm | ki, L/min/cm/s | MSE, cm^2 |
| --- | --- | --- | --- |
| untuned (registered gains) | {reg["kp"]:.4g} | {reg["ki"]:.4g} | {s["mse_untuned_cm2"]:.4g} |
| tuned by pitune, {s["gain_updates"]} updates | {fin["kp"]:.4g} | {fin["ki"]:.4g} | \
{s["mse_tuned_cm2"]:.4g} |

{_noise_note(s)}The tuned loop tracks the target {s["improvement"]:.1f}x better (MSE ratio). \
For reference,
improved SIMC on the tank's linearisation {lin["k"]:g} exp(-{lin["theta_s"]:g} s)/\
({lin["tau_s"]:g} s + 1) with tau_c = {2 * lin["tau_s"]:g} s gives kp = {simc["kp"]:.3g} \
(L/min)/cm, ki = {simc["ki"]:.3g} (L/min)/(cm s).
"""


class Progress:
    """The live progress line: simulated time, gains in force, recent tracking error."""

    WINDOW_S = 600.0

    def __init__(self, duration_s: float) -> None:
        self.duration_s = duration_s
        self.tty = sys.stdout.isatty()
        self.next_line_t = 0.0

    def show(self, view: dict, log: Path, *, final: bool = False) -> None:
        t = view.get("last_sample_t")
        if t is None:
            return
        rms = self.recent_rms(log, t)
        line = (
            f"sim {t / 60:5.1f}/{self.duration_s / 60:g} min | kp {view['kp']:.4g} L/min/cm | "
            f"ki {view['ki']:.3g} L/min/cm/s | updates {view['seq']:3d} | "
            f"level-target RMS, last {self.WINDOW_S / 60:g} min: "
            + ("-" if rms is None else f"{rms:.2f} cm")
        )
        if self.tty:
            print("\r" + line, end="\n" if final else "", flush=True)
        elif final or t >= self.next_line_t:
            print(line, flush=True)
            self.next_line_t = t + self.duration_s / 10

    def recent_rms(self, log: Path, t: float) -> float | None:
        try:
            traj = read_log(log)
        except (OSError, ValueError):  # not written yet, or a partial first line
            return None
        recent = traj.t > t - self.WINDOW_S
        if not recent.any():
            return None
        return float(np.sqrt(np.mean(traj.tracking_error()[recent] ** 2)))
