"""``pitune plant``: simulated loops behind a DCS-like gateway on the Zenoh bus.

``pitune plant run`` simulates one or more loops in simulated time (``--speed`` times
real time, 0 for as fast as possible) and, every DCS scan of simulated time, publishes
a :class:`~service.wire.protocol.Sample` per loop in engineering units with the gains in
force (:mod:`plant_sim.runner`). Gains messages whose mode is ``auto`` are applied
bumplessly, clipped to the loop's own bounds (``--gain-range`` around its initial
gains), and reported applied (``applied_seq``), so the tuner adopts gains clipped;
``advisory`` ones are only counted. ``--register URL`` registers the loops with
the tuner's admin API first (:mod:`plant_sim.registration`), with the paper's crude
model hint (1.2 cm/(L/min), 30 s, PV scale 10 cm for the tank). ``--log-dir`` writes one
CSV trajectory per loop, which ``pitune plant plot`` draws. ``--gateway-id`` also
receives the batched gains of loops registered with that gateway (and registers them so).

This module is the command line only: it turns the arguments into a
:class:`~plant_sim.config.PlantConfig` once (:func:`plant_config`), and
:func:`plant_argv` writes one back as arguments for a ``pitune plant run`` subprocess.
Loop syntax: :mod:`plant_sim.config`.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from dataclasses import fields
from pathlib import Path

from plant_sim.config import DEFAULT_LOOPS, LoopSpec, PlantConfig, Simulation, build_loops
from plant_sim.registration import register
from plant_sim.runner import simulate
from plant_sim.trajectory import plot, read_log
from service.gateways.registration import RegistrationError
from service.wire.protocol import DEFAULT_PREFIX, is_valid_id

TOKEN_ENV = "PITUNE_API_TOKEN"
SIM = Simulation()
"""The simulation defaults, which the options' defaults are."""
KIND_OPTIONS = {"two_tank": "--tank", "foptd": "--foptd"}


# -- command line ----------------------------------------------------------------------
def _gateway_id(text: str) -> str:
    if not is_valid_id(text):
        raise argparse.ArgumentTypeError(f"invalid gateway id {text!r}")
    return text


def _loop_spec(kind: str):
    def parse(text: str) -> LoopSpec:
        try:
            return LoopSpec.parse(kind, text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    return parse


def _at_least(low: float, *, strict: bool = False):
    """An argparse type: a finite number >= ``low`` (> with ``strict``), else a clear error."""

    def parse(text: str) -> float:
        value = float(text)
        if not (math.isfinite(value) and (value > low if strict else value >= low)):
            raise argparse.ArgumentTypeError(f"{text}: must be {'>' if strict else '>='} {low:g}")
        return value

    return parse


def seed(text: str) -> int:
    """An argparse type: a random seed, an integer >= 0 (numpy refuses a negative one, which
    would end the run after its processes started)."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text}: must be >= 0")
    return value


def _image_file(text: str) -> Path:
    """An argparse type: a file name whose suffix matplotlib writes (checked before the
    logs are read, not by a traceback at the end)."""
    from matplotlib.backend_bases import FigureCanvasBase

    formats = FigureCanvasBase.get_supported_filetypes()
    if Path(text).suffix.lower().lstrip(".") not in formats:
        raise argparse.ArgumentTypeError(f"{text}: give a file ending in .{', .'.join(formats)}")
    return Path(text)


def add_loop_arguments(run_p: argparse.ArgumentParser) -> None:
    """``--tank``, ``--foptd`` and the ``simulation`` options, read by :func:`plant_config`
    (and by any other simulator front end)."""
    run_p.add_argument(
        "--tank",
        dest="loops",
        action="append",
        type=_loop_spec("two_tank"),
        metavar="ID[:k=v,...]",
        help="a two-tank level loop (default: one, 'tank1', if no loop is given)",
    )
    run_p.add_argument(
        "--foptd",
        dest="loops",
        action="append",
        type=_loop_spec("foptd"),
        metavar="ID:K=..,tau=..,theta=..[,k=v]",
        help="an FOPTD loop K exp(-theta s)/(tau s + 1), seconds (K < 0: a cooling-like "
        "loop, run and registered direct-acting)",
    )
    sim = run_p.add_argument_group("simulation")
    sim.add_argument(
        "--scan", type=_at_least(1e-3), default=SIM.scan, help="DCS scan interval, s (1)"
    )
    sim.add_argument(
        "--speed",
        type=_at_least(0.0),
        default=SIM.speed,
        help="simulated s per wall s; 0 = as fast as possible",
    )
    sim.add_argument(
        "--duration",
        type=_at_least(0.0, strict=True),
        default=SIM.duration,
        help="stop after this many simulated s",
    )
    sim.add_argument(
        "--t0",
        type=_at_least(-math.inf),  # any finite time
        default=SIM.t0,
        help="plant clock at start, s (0); a loop the tuner knows resumes after its last sample",
    )
    sim.add_argument(
        "--sp-period",
        type=_at_least(0.0, strict=True),
        default=SIM.sp_period,
        help="s between setpoint steps (600)",
    )
    sim.add_argument(
        "--noise",
        type=_at_least(0.0),
        default=SIM.noise,
        help="uniform measurement noise +-N, PV units",
    )
    sim.add_argument(
        "--load",
        type=float,
        default=SIM.load,
        help="load step, OP units, on and off midway between setpoint steps",
    )
    sim.add_argument(
        "--gain-range",
        type=_at_least(1.0, strict=True),  # R <= 1: no range, or gains moved by the plant
        default=SIM.gain_range,
        help="accepted gains lie within initial/R..initial*R (100)",
    )
    sim.add_argument("--seed", type=seed, default=SIM.seed)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="plant_command", metavar="ACTION", required=True)
    run_p = sub.add_parser("run", help="simulate loops and exchange samples/gains over Zenoh")
    add_loop_arguments(run_p)
    bus = run_p.add_argument_group("bus")
    bus.add_argument("--prefix", default=DEFAULT_PREFIX, help="key-expression prefix")
    bus.add_argument(
        "--mode", choices=("peer", "client"), default=None, help="Zenoh mode (default: peer)"
    )
    bus.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="Zenoh endpoint of the tuner or router, e.g. tcp/127.0.0.1:7447 (repeatable)",
    )
    bus.add_argument(
        "--listen", action="append", default=[], metavar="ENDPOINT", help="listen here too"
    )
    bus.add_argument(
        "--zenoh-config", default=None, metavar="FILE", help="Zenoh JSON5 config (auth, TLS)"
    )
    bus.add_argument(
        "--gateway-id",
        default=None,
        type=_gateway_id,
        metavar="ID",
        help="receive batched gains on {prefix}/gateways/ID/gains (and register the loops "
        "with this gateway when --register is given)",
    )
    reg = run_p.add_argument_group("registration")
    reg.add_argument("--register", default=None, metavar="URL", help="tuner admin API base URL")
    reg.add_argument(
        "--register-timeout", type=float, default=60.0, help="wait this long for the API, s"
    )
    reg.add_argument(
        "--tuner-lag",
        type=_at_least(0.0),
        default=0.0,
        metavar="S",
        help="wait for the tuner when it has not accepted the samples of S simulated s "
        "ago (0 = never: a real plant's pace; pitune demo sets it so that a busy machine "
        "slows the run instead of delaying the gains in simulated time)",
    )
    out = run_p.add_argument_group("output")
    out.add_argument("--log-dir", type=Path, default=None, help="write DIR/<loop id>.csv")
    out.add_argument(
        "--progress", type=float, default=600.0, help="status line every N simulated s (0: off)"
    )

    plot_p = sub.add_parser("plot", help="draw trajectory logs (CSV) as a PNG")
    plot_p.add_argument("logs", nargs="+", type=Path, help="logs; the first one's target is drawn")
    image = "image file: PNG, or another format by its suffix (.svg, .pdf)"
    plot_p.add_argument("-o", "--out", type=_image_file, required=True, help=image)
    plot_p.add_argument("--title", default="")


def simulation(args: argparse.Namespace) -> Simulation:
    """The ``simulation`` options of :func:`add_loop_arguments` as a :class:`Simulation`."""
    return Simulation(**{f.name: getattr(args, f.name) for f in fields(Simulation)})


def plant_config(args: argparse.Namespace) -> PlantConfig:
    """The parsed ``pitune plant run`` arguments as a :class:`PlantConfig`."""
    try:
        return PlantConfig(
            loops=tuple(args.loops or DEFAULT_LOOPS),
            sim=simulation(args),
            prefix=args.prefix,
            mode=args.mode,
            connect=tuple(args.connect),
            listen=tuple(args.listen),
            zenoh_config=args.zenoh_config,
            gateway_id=args.gateway_id,
            register=args.register,
            register_timeout=args.register_timeout,
            log_dir=args.log_dir,
            progress=args.progress,
            tuner_lag=args.tuner_lag,
        )
    except ValueError as exc:
        raise SystemExit(f"pitune plant: {exc}") from None


def plant_argv(loops: tuple[LoopSpec, ...], sim: Simulation) -> list[str]:
    """``pitune plant run`` options for these loops and simulation settings (the ones
    that differ from the defaults); :func:`plant_config` reads them back."""
    argv = [arg for spec in loops for arg in (KIND_OPTIONS[spec.kind], spec.text())]
    for name, value in sim.changed().items():
        argv += [f"--{name.replace('_', '-')}", repr(value)]
    return argv


def run(args: argparse.Namespace) -> int:
    if args.plant_command == "plot":
        try:
            runs = {path.stem: read_log(path) for path in args.logs}
        except ValueError as exc:  # a file that is not a log (a missing one: cli.py's)
            print(f"pitune plant plot: {exc}", file=sys.stderr)
            return 1
        print(plot(runs, args.out, title=args.title))
        return 0
    config = plant_config(args)
    known = {}
    if config.register:
        try:
            known = register(
                config.register,
                config.loops,
                scan=config.sim.scan,
                token=os.environ.get(TOKEN_ENV),
                timeout=config.register_timeout,
                gateway=config.gateway_id,
            )
        except RegistrationError as exc:
            print(f"pitune plant: {exc}", file=sys.stderr)
            return 1
    return simulate(config, build_loops(config.loops, config.sim, known))
