"""``pitune plant``: simulated loops behind a DCS-like gateway on the Zenoh bus.

``pitune plant run`` simulates one or more loops in simulated time (``--speed`` times
real time, 0 for as fast as possible) and, every DCS scan of simulated time, publishes
a :class:`~service.wire.protocol.Sample` per loop in engineering units with the gains in
force. Gains messages whose mode is ``auto`` are applied bumplessly, clipped to the
loop's own bounds (``--gain-range`` around its initial gains); ``advisory`` ones are
only counted. ``--register URL`` registers the loops with the tuner's admin API first,
with the paper's crude model hint (1.2 cm/(L/min), 30 s, PV scale 10 cm for the tank).
``--log-dir`` writes one CSV trajectory per loop, which ``pitune plant plot`` draws.
``--gateway-id`` also receives the batched gains of loops registered with that gateway
(and registers them so). The bus side follows docs/protocol.md (:mod:`plant_sim.gateway`).

Loops are given as ``--tank ID[:key=value,...]`` and ``--foptd ID:K=..,tau=..,theta=..``
(seconds and engineering units); optional keys: ``kp``, ``ki`` (initial gains, default
the paper's untuned ones for the model hint), ``lo``, ``hi`` (setpoint steps),
``k_hat``, ``tau_hat``, ``pv_scale`` (model hint for registration; an FOPTD loop's
default hint is its true model).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, closing
from dataclasses import dataclass
from pathlib import Path

import httpx
import zenoh

from plant_sim.gateway import Gateway
from plant_sim.scenario import (
    TANK_HINT,
    TANK_PV_SCALE,
    FoptdLoop,
    LoopSettings,
    Scan,
    SimulatedLoop,
    TankLoop,
)
from plant_sim.trajectory import Trajectory, TrajectoryWriter, plot, read_log
from service.units import ScalingSpec
from service.wire.protocol import DEFAULT_PREFIX, Keys, Mode, Sample, is_valid_id
from service.wire.session import session_config

TANK_SP = (50.0, 60.0)
SP_PERIOD_S = 600.0
"""The tank's setpoint toggles every 10 simulated minutes, as in the paper's figure 10."""
UNTUNED_AGENT_GAINS = (0.05, 0.05)
"""The paper's initial Kc = 0.05, tau_I = 1 time unit, as agent (kp, ki)."""
TOKEN_ENV = "PITUNE_API_TOKEN"


@dataclass(frozen=True)
class LoopSpec:
    """One ``--tank`` or ``--foptd`` argument, parsed."""

    kind: str
    loop_id: str
    params: dict[str, float]

    FOPTD_REQUIRED = ("K", "tau", "theta")
    COMMON = ("kp", "ki", "lo", "hi", "k_hat", "tau_hat", "pv_scale")

    @classmethod
    def parse(cls, kind: str, text: str) -> LoopSpec:
        loop_id, _, rest = text.partition(":")
        if not is_valid_id(loop_id):
            raise argparse.ArgumentTypeError(f"invalid loop id {loop_id!r}")
        params: dict[str, float] = {}
        for item in filter(None, rest.split(",")):
            key, eq, value = item.partition("=")
            allowed = cls.COMMON + (cls.FOPTD_REQUIRED if kind == "foptd" else ())
            if not eq or key not in allowed:
                raise argparse.ArgumentTypeError(
                    f"{text!r}: expected key=value with key in {', '.join(allowed)}"
                )
            try:
                params[key] = float(value)
            except ValueError:
                raise argparse.ArgumentTypeError(f"{text!r}: {key} is not a number") from None
        missing = [k for k in cls.FOPTD_REQUIRED if kind == "foptd" and k not in params]
        if missing:
            raise argparse.ArgumentTypeError(f"{text!r}: missing {', '.join(missing)}")
        return cls(kind, loop_id, params)

    def hint(self) -> ScalingSpec:
        """The crude model the loop is registered with."""
        p = self.params
        if self.kind == "two_tank":
            k_hat, tau_hat, pv_scale = (*TANK_HINT, TANK_PV_SCALE)
        else:
            k_hat, tau_hat = p["K"], p["tau"]
            pv_scale = (p.get("hi", 1.0) - p.get("lo", -1.0)) / 2.0
        return ScalingSpec(
            k_hat=p.get("k_hat", k_hat),
            tau_hat=p.get("tau_hat", tau_hat),
            pv_scale=p.get("pv_scale", pv_scale),
        )

    def initial_gains(self) -> tuple[float, float]:
        """``kp``/``ki`` if given, else the paper's slow initial tuning through the hint."""
        kp0, ki0 = self.hint().resolve().to_engineering(*UNTUNED_AGENT_GAINS)
        return self.params.get("kp", kp0), self.params.get("ki", ki0)

    def registration(self, scan: float, gateway: str | None = None) -> dict:
        """Body of ``POST /loops`` (:class:`service.engine.config.LoopConfig`); with ``gateway``,
        the tuner sends the loop's gains in that gateway's batches."""
        kp, ki = self.initial_gains()
        body = {
            "id": self.loop_id,
            "kp": kp,
            "ki": ki,
            "sample_period_s": scan,
            "scaling": self.hint().model_dump(exclude_none=True),
        }
        if gateway is not None:
            body["gateway"] = gateway
        return body

    def build(self, args: argparse.Namespace, *, seed: int, t0: float) -> SimulatedLoop:
        p = self.params
        kp, ki = self.initial_gains()
        lo, hi = TANK_SP if self.kind == "two_tank" else (-1.0, 1.0)
        settings = LoopSettings(
            kp=kp,
            ki=ki,
            sp_low=p.get("lo", lo),
            sp_high=p.get("hi", hi),
            sp_period=args.sp_period,
            load=args.load,
            noise=args.noise,
            gain_range=args.gain_range,
        )
        common = {"dt": args.scan, "seed": seed, "t0": t0}
        if self.kind == "two_tank":
            return TankLoop(self.loop_id, settings, **common)
        return FoptdLoop(self.loop_id, settings, K=p["K"], tau=p["tau"], theta=p["theta"], **common)


def loop_specs(args: argparse.Namespace) -> list[LoopSpec]:
    """The loops named on the command line, or one default tank, ``tank1``."""
    specs = args.loops or [LoopSpec("two_tank", "tank1", {})]
    ids = [s.loop_id for s in specs]
    if len(set(ids)) != len(ids):
        raise SystemExit(f"pitune plant: duplicate loop ids in {ids}")
    return specs


def to_sample(scan: Scan) -> Sample:
    return Sample(
        t=scan.t, sp=scan.sp, pv=scan.pv, kp=scan.kp, ki=scan.ki, saturated=scan.saturated
    )


class RegistrationError(RuntimeError):
    pass


def register(
    url: str,
    specs: list[LoopSpec],
    *,
    scan: float,
    token: str | None,
    timeout: float,
    gateway: str | None = None,
) -> dict[str, dict]:
    """Register each loop with the tuner (``POST /loops``); return the views of loops the
    tuner already had (HTTP 409), which a restarted simulator resumes.

    Retries connection failures until ``timeout``: the tuner may still be starting.
    """
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    deadline = time.monotonic() + timeout
    known = {}
    with httpx.Client(base_url=url, headers=headers, timeout=10.0) as client:

        def call(method: str, path: str, **kw) -> httpx.Response:
            while True:
                try:
                    return client.request(method, path, **kw)
                except httpx.TransportError as exc:
                    if time.monotonic() > deadline:
                        raise RegistrationError(f"tuner API at {url} unreachable: {exc}") from exc
                    time.sleep(0.2)

        for spec in specs:
            response = call("POST", "/loops", json=spec.registration(scan, gateway))
            if response.status_code == 409:
                response = call("GET", f"/loops/{spec.loop_id}")
                if response.is_success:
                    known[spec.loop_id] = response.json()
                    continue
            if not response.is_success:
                raise RegistrationError(
                    f"registering {spec.loop_id} failed: HTTP {response.status_code} "
                    f"{response.text[:300]}"
                )
    return known


def build_loops(
    args: argparse.Namespace, specs: list[LoopSpec], known: dict[str, dict]
) -> list[SimulatedLoop]:
    """The simulated loops, seeded apart. Loops the tuner already knows resume: the plant
    clock starts one scan after the tuner's last sample (it rejects older ones) and the
    PI starts with the tuner's gains, as a DCS keeps its gains across a gateway restart."""
    last_t = [v["last_sample_t"] for v in known.values() if v.get("last_sample_t") is not None]
    t0 = max([args.t0, *(t + args.scan for t in last_t)])
    loops = []
    for i, spec in enumerate(specs):
        loop = spec.build(args, seed=args.seed + i, t0=t0)
        if spec.loop_id in known:
            loop.apply_gains(known[spec.loop_id]["kp"], known[spec.loop_id]["ki"])
        loops.append(loop)
    return loops


class StopFlag:
    """Set by SIGINT or SIGTERM: the plant finishes its scan and exits cleanly."""

    def __init__(self) -> None:
        self.set = False
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._handle)

    def _handle(self, signum: int, frame: object) -> None:
        self.set = True

    def __call__(self) -> bool:
        return self.set


def paced(dt: float, speed: float, stop: Callable[[], bool]) -> Iterator[int]:
    """Scan numbers 0, 1, ... released at ``speed`` times real time (0: no waiting)."""
    start = time.monotonic()
    k = 0
    while not stop():
        if speed > 0:
            delay = start + k * dt / speed - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        yield k
        k += 1


def simulate(args: argparse.Namespace, loops: list[SimulatedLoop]) -> int:
    """Run the loops on the bus until ``--duration`` or a signal; always close the session."""
    stop = StopFlag()
    by_id = {loop.loop_id: loop for loop in loops}
    config = session_config(
        config_file=args.zenoh_config,
        mode=args.mode,
        connect=args.connect or None,
        listen=args.listen or None,
    )
    session = zenoh.open(config)
    try:
        gateway = Gateway(session, list(by_id), Keys(args.prefix), gateway_id=args.gateway_id)
        print(
            f"plant: {', '.join(by_id)} on the bus, scan {args.scan:g} s, speed {args.speed:g}x"
            if args.speed
            else "plant: running as fast as possible",
            flush=True,
        )
        with ExitStack() as stack:
            writers = {
                loop_id: stack.enter_context(
                    closing(TrajectoryWriter(args.log_dir / f"{loop_id}.csv"))
                )
                for loop_id in (by_id if args.log_dir else ())
            }
            applied, ignored = run_scans(args, loops, gateway, writers, stop)
        gateway.close()
        print(
            f"plant stopped: {applied} gain updates applied, {ignored} advisory ignored, "
            f"{gateway.inbox.invalid} invalid and {gateway.inbox.stale} stale messages dropped",
            flush=True,
        )
    finally:
        session.close()
    return 0


def run_scans(
    args: argparse.Namespace,
    loops: list[SimulatedLoop],
    gateway: Gateway,
    writers: dict[str, TrajectoryWriter],
    stop: Callable[[], bool],
) -> tuple[int, int]:
    """The scan loop; returns (gain updates applied, advisory updates ignored)."""
    by_id = {loop.loop_id: loop for loop in loops}
    applied = ignored = 0
    progress_every = round(args.progress / args.scan) if args.progress > 0 else 0
    last = round(args.duration / args.scan) if args.duration is not None else None
    for k in paced(args.scan, args.speed, stop):
        if last is not None and k >= last:
            break
        for msg in gateway.gains():  # seq rule applied, state replies included
            if msg.mode == Mode.auto:
                by_id[msg.loop_id].apply_gains(msg.kp, msg.ki)
                applied += 1
            else:
                ignored += 1
        for loop in loops:
            scan = loop.scan()
            gateway.publish(loop.loop_id, to_sample(scan))
            if loop.loop_id in writers:
                writers[loop.loop_id].write(scan)
            if progress_every and k % progress_every == 0:
                print(
                    f"t={scan.t:9.0f}s {loop.loop_id}: sp={scan.sp:.4g} pv={scan.pv:.4g} "
                    f"op={scan.op:.4g} kp={scan.kp:.4g} ki={scan.ki:.4g}",
                    flush=True,
                )
    return applied, ignored


# -- command line ----------------------------------------------------------------------
def _gateway_id(text: str) -> str:
    if not is_valid_id(text):
        raise argparse.ArgumentTypeError(f"invalid gateway id {text!r}")
    return text


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="plant_command", metavar="ACTION", required=True)
    run_p = sub.add_parser("run", help="simulate loops and exchange samples/gains over Zenoh")
    run_p.add_argument(
        "--tank",
        dest="loops",
        action="append",
        type=lambda s: LoopSpec.parse("two_tank", s),
        metavar="ID[:k=v,...]",
        help="a two-tank level loop (default: one, 'tank1', if no loop is given)",
    )
    run_p.add_argument(
        "--foptd",
        dest="loops",
        action="append",
        type=lambda s: LoopSpec.parse("foptd", s),
        metavar="ID:K=..,tau=..,theta=..[,k=v]",
        help="an FOPTD loop K exp(-theta s)/(tau s + 1), seconds",
    )
    sim = run_p.add_argument_group("simulation")
    sim.add_argument("--scan", type=float, default=1.0, help="DCS scan interval, s (1)")
    sim.add_argument(
        "--speed", type=float, default=1.0, help="simulated s per wall s; 0 = as fast as possible"
    )
    sim.add_argument(
        "--duration", type=float, default=None, help="stop after this many simulated s"
    )
    sim.add_argument(
        "--t0",
        type=float,
        default=0.0,
        help="plant clock at start, s (0); a loop the tuner knows resumes after its last sample",
    )
    sim.add_argument(
        "--sp-period", type=float, default=SP_PERIOD_S, help="s between setpoint steps (600)"
    )
    sim.add_argument(
        "--noise", type=float, default=0.0, help="uniform measurement noise +-N, PV units"
    )
    sim.add_argument(
        "--load",
        type=float,
        default=0.0,
        help="load step, OP units, on and off midway between setpoint steps",
    )
    sim.add_argument(
        "--gain-range",
        type=float,
        default=100.0,
        help="accepted gains lie within initial/R..initial*R (100)",
    )
    sim.add_argument("--seed", type=int, default=0)
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
    out = run_p.add_argument_group("output")
    out.add_argument("--log-dir", type=Path, default=None, help="write DIR/<loop id>.csv")
    out.add_argument(
        "--progress", type=float, default=600.0, help="status line every N simulated s (0: off)"
    )

    plot_p = sub.add_parser("plot", help="draw trajectory logs (CSV) as a PNG")
    plot_p.add_argument("logs", nargs="+", type=Path, help="logs; the first one's target is drawn")
    plot_p.add_argument("-o", "--out", type=Path, required=True, help="PNG file")
    plot_p.add_argument("--title", default="")


def run(args: argparse.Namespace) -> int:
    if args.plant_command == "plot":
        runs = {path.stem: read_log(path) for path in args.logs}
        print(plot(runs, args.out, title=args.title))
        return 0
    specs = loop_specs(args)
    known = {}
    if args.register:
        try:
            known = register(
                args.register,
                specs,
                scan=args.scan,
                token=os.environ.get(TOKEN_ENV),
                timeout=args.register_timeout,
                gateway=args.gateway_id,
            )
        except RegistrationError as exc:
            print(f"pitune plant: {exc}", file=sys.stderr)
            return 1
    return simulate(args, build_loops(args, specs, known))


def untuned_baseline(args: argparse.Namespace) -> dict[str, Trajectory]:
    """The loops of ``args`` for ``--duration`` without a bus: same plant, schedule and
    noise (same seed), gains fixed at their initial values. The demo's comparison run."""
    loops = build_loops(args, loop_specs(args), {})
    scans = round(args.duration / args.scan)
    return {
        loop.loop_id: Trajectory.from_scans([loop.scan() for _ in range(scans)]) for loop in loops
    }
