"""A plant simulator run as data: its loops, the simulation they share, the bus and outputs.

``pitune plant run`` parses its command line into a :class:`PlantConfig` once
(:mod:`plant_sim.process`); everything below takes these dataclasses, so the demo and
the tests build a run in Python and :func:`untuned_baseline` replays the same loops
in-process, without a bus.

Loops are given as ``--tank ID[:key=value,...]`` and ``--foptd ID:K=..,tau=..,theta=..``
(:meth:`LoopSpec.parse`, seconds and engineering units); optional keys: ``kp``, ``ki``
(initial gains, default the paper's untuned ones for the model hint), ``lo``, ``hi``
(setpoint steps), ``k_hat``, ``tau_hat``, ``pv_scale`` (model hint for registration;
an FOPTD loop's default hint is its true model). A negative ``K`` simulates a process
whose PV falls as the output rises (cooling, a level drained by the manipulated flow):
its PI is direct-acting and the loop is registered with ``action: "direct"``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from pathlib import Path

from pydantic import ValidationError

from plant_sim.scenario import (
    TANK_HINT,
    TANK_PV_SCALE,
    FoptdLoop,
    LoopSettings,
    SimulatedLoop,
    TankLoop,
)
from plant_sim.trajectory import Trajectory
from service.units import AGENT_KI0, AGENT_KP0, ScalingSpec
from service.wire.protocol import DEFAULT_PREFIX, is_valid_id

SP_DEFAULTS = {"two_tank": (50.0, 60.0), "foptd": (-1.0, 1.0)}
"""Each kind's setpoint levels (lo, hi) where ``lo``/``hi`` are not given."""
TANK_MAX_SP = 100.0
"""Highest tank setpoint, cm: the full pump (80 L/min) holds 101 cm."""
SP_PERIOD_S = 600.0
"""The tank's setpoint toggles every 10 simulated minutes, as in the paper's figure 10."""


def _in_range(key: str, value: float) -> bool:
    """Loop parameters: PV limits any finite numbers, K nonzero (negative: a direct-acting
    loop), dead time >= 0, the rest > 0."""
    if not math.isfinite(value):
        return False
    if key in ("lo", "hi"):
        return True
    if key == "K":
        return value != 0.0
    return value >= 0.0 if key == "theta" else value > 0.0


@dataclass(frozen=True)
class LoopSpec:
    """One simulated loop: ``kind`` (``two_tank`` or ``foptd``), id and parameters."""

    kind: str
    loop_id: str
    params: dict[str, float] = field(default_factory=dict)

    FOPTD_REQUIRED = ("K", "tau", "theta")
    COMMON = ("kp", "ki", "lo", "hi", "k_hat", "tau_hat", "pv_scale")

    @classmethod
    def parse(cls, kind: str, text: str) -> LoopSpec:
        """``ID[:key=value,...]``, as on the command line; ValueError says what is wrong."""
        loop_id, _, rest = text.partition(":")
        if not is_valid_id(loop_id):
            raise ValueError(f"invalid loop id {loop_id!r}")
        params: dict[str, float] = {}
        for item in filter(None, rest.split(",")):
            key, eq, value = item.partition("=")
            allowed = cls.COMMON + (cls.FOPTD_REQUIRED if kind == "foptd" else ())
            if not eq or key not in allowed:
                raise ValueError(f"{text!r}: expected key=value with key in {', '.join(allowed)}")
            try:
                params[key] = float(value)
            except ValueError:
                raise ValueError(f"{text!r}: {key} is not a number") from None
        missing = [k for k in cls.FOPTD_REQUIRED if kind == "foptd" and k not in params]
        if missing:
            raise ValueError(f"{text!r}: missing {', '.join(missing)}")
        bad = [k for k, v in params.items() if not _in_range(k, v)]
        lo, hi = params.get("lo", SP_DEFAULTS[kind][0]), params.get("hi", SP_DEFAULTS[kind][1])
        if lo >= hi:  # against the kind's own defaults: a tank's are 50 and 60 cm
            bad.append("lo < hi")
        if kind == "two_tank" and not 0.0 < lo < hi <= TANK_MAX_SP:
            bad.append(f"tank setpoints within (0, {TANK_MAX_SP:g}] cm (what the pump holds)")
        if bad:
            raise ValueError(
                f"{text!r}: {', '.join(bad)} out of range (K nonzero; tau, gains and hints "
                "> 0; theta >= 0)"
            )
        spec = cls(kind, loop_id, params)
        try:
            spec.initial_gains()
        except ValidationError as exc:
            raise ValueError(f"{text!r}: {exc.errors()[0]['msg']}") from None
        return spec

    def text(self) -> str:
        """The command-line form :meth:`parse` reads back."""
        items = ",".join(f"{k}={v!r}" for k, v in self.params.items())
        return f"{self.loop_id}:{items}" if items else self.loop_id

    def hint(self) -> ScalingSpec:
        """The crude model the loop is registered with."""
        p = self.params
        if self.kind == "two_tank":
            k_hat, tau_hat, pv_scale = (*TANK_HINT, TANK_PV_SCALE)
        else:
            k_hat, tau_hat = abs(p["K"]), p["tau"]
            pv_scale = (p.get("hi", 1.0) - p.get("lo", -1.0)) / 2.0
        return ScalingSpec(
            k_hat=p.get("k_hat", k_hat),
            tau_hat=p.get("tau_hat", tau_hat),
            pv_scale=p.get("pv_scale", pv_scale),
        )

    @property
    def action(self) -> str:
        """The PI's controller action: 'direct' for a negative-gain process."""
        return "direct" if self.params.get("K", 1.0) < 0 else "reverse"

    def initial_gains(self) -> tuple[float, float]:
        """``kp``/``ki`` if given, else the paper's slow initial tuning through the hint."""
        kp0, ki0 = self.hint().resolve().to_engineering(AGENT_KP0, AGENT_KI0)
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
        if self.action == "direct":
            body["action"] = self.action
        if gateway is not None:
            body["gateway"] = gateway
        return body

    def build(self, sim: Simulation, *, seed: int, t0: float) -> SimulatedLoop:
        p = self.params
        kp, ki = self.initial_gains()
        lo, hi = SP_DEFAULTS[self.kind]
        settings = LoopSettings(
            kp=kp,
            ki=ki,
            sp_low=p.get("lo", lo),
            sp_high=p.get("hi", hi),
            sp_period=sim.sp_period,
            load=sim.load,
            noise=sim.noise,
            gain_range=sim.gain_range,
            action=self.action,
        )
        common = {"dt": sim.scan, "seed": seed, "t0": t0}
        if self.kind == "two_tank":
            return TankLoop(self.loop_id, settings, **common)
        return FoptdLoop(self.loop_id, settings, K=p["K"], tau=p["tau"], theta=p["theta"], **common)


DEFAULT_LOOPS = (LoopSpec("two_tank", "tank1"),)
"""Without loops on the command line the simulator runs one tank, ``tank1``."""


@dataclass(frozen=True)
class Simulation:
    """What all loops of a run share: clock, schedule, disturbances, limits, seed."""

    scan: float = 1.0
    """DCS scan interval, s."""
    speed: float = 1.0
    """Simulated seconds per wall second; 0 runs as fast as possible."""
    duration: float | None = None
    """Stop after this many simulated seconds (None: until stopped)."""
    t0: float = 0.0
    """Plant clock at start, s; a loop the tuner knows resumes after its last sample."""
    sp_period: float = SP_PERIOD_S
    """Seconds between setpoint steps."""
    noise: float = 0.0
    """Uniform measurement noise +-N, PV units."""
    load: float = 0.0
    """Load step, OP units, on and off midway between setpoint steps."""
    gain_range: float = 100.0
    """Accepted gains lie within initial/R..initial*R."""
    seed: int = 0

    def changed(self) -> dict[str, object]:
        """The settings that differ from the defaults, by name."""
        return {f.name: v for f in fields(self) if (v := getattr(self, f.name)) != f.default}


@dataclass(frozen=True)
class PlantConfig:
    """One ``pitune plant run``: loops, simulation, bus, registration and outputs."""

    loops: tuple[LoopSpec, ...] = DEFAULT_LOOPS
    sim: Simulation = Simulation()
    prefix: str = DEFAULT_PREFIX
    mode: str | None = None
    """Zenoh mode, ``peer`` or ``client`` (None: the session's default, peer)."""
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    zenoh_config: str | None = None
    gateway_id: str | None = None
    """Also receive the batched gains of this gateway (and register the loops with it)."""
    register: str | None = None
    """The tuner's admin API base URL to register the loops with first."""
    register_timeout: float = 60.0
    log_dir: Path | None = None
    """Write one trajectory CSV per loop here."""
    progress: float = 600.0
    """A status line every N simulated seconds (0: off)."""
    tuner_lag: float = 0.0
    """Simulated seconds the plant may run ahead of the last sample the tuner accepted
    before it waits for the tuner (0: never waits, as a real plant). A plant at a high
    ``speed`` on a busy machine otherwise outruns its tuner: gains computed on a sample
    reach it minutes of simulated time later (``plant_sim.runner.TunerPace``)."""

    def __post_init__(self) -> None:
        ids = [s.loop_id for s in self.loops]
        if len(set(ids)) != len(ids):
            raise ValueError(f"duplicate loop ids in {ids}")


def build_loops(
    specs: tuple[LoopSpec, ...], sim: Simulation, known: dict[str, dict]
) -> list[SimulatedLoop]:
    """The simulated loops, seeded apart. Loops the tuner already knows (their views by
    id) resume: the plant clock starts one scan after the tuner's last sample (it rejects
    older ones) and the PI starts with the tuner's gains, as a DCS keeps its gains across
    a gateway restart."""
    last_t = [v["last_sample_t"] for v in known.values() if v.get("last_sample_t") is not None]
    t0 = max([sim.t0, *(t + sim.scan for t in last_t)])
    loops = []
    for i, spec in enumerate(specs):
        loop = spec.build(sim, seed=sim.seed + i, t0=t0)
        if spec.loop_id in known:
            loop.apply_gains(known[spec.loop_id]["kp"], known[spec.loop_id]["ki"])
        loops.append(loop)
    return loops


def untuned_baseline(specs: tuple[LoopSpec, ...], sim: Simulation) -> dict[str, Trajectory]:
    """The loops for ``sim.duration`` without a bus: same plant, schedule and noise (same
    seed), gains fixed at their initial values. The demo's comparison run."""
    scans = round(sim.duration / sim.scan)
    return {
        loop.loop_id: Trajectory.from_scans([loop.scan() for _ in range(scans)])
        for loop in build_loops(specs, sim, {})
    }
