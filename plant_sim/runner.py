"""The simulator's scan loop on the bus: paced in simulated time, samples out, gains in.

Every DCS scan of simulated time (``speed`` times real time, 0 for as fast as possible)
each loop publishes a :class:`~service.wire.protocol.Sample` in engineering units with
the gains in force. Gains messages whose mode is ``auto`` are applied bumplessly,
clipped to the loop's own bounds; ``advisory`` ones are only counted. The bus side
follows docs/protocol.md (:mod:`service.gateways.base`).
"""

from __future__ import annotations

import signal
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, closing

import zenoh

from plant_sim.config import PlantConfig
from plant_sim.scenario import Scan, SimulatedLoop
from plant_sim.trajectory import TrajectoryWriter
from service.gateways.base import Gateway
from service.wire.protocol import Keys, Mode, Sample
from service.wire.session import session_config


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


def to_sample(scan: Scan) -> Sample:
    return Sample(
        t=scan.t, sp=scan.sp, pv=scan.pv, kp=scan.kp, ki=scan.ki, saturated=scan.saturated
    )


EXIT_NO_TUNER = 3
"""Exit status of a run that registered its loops but never heard a tuner on the bus."""


def simulate(config: PlantConfig, loops: list[SimulatedLoop]) -> int:
    """Run the loops on the bus until the duration or a signal; always close the session.

    Exits 0, or :data:`EXIT_NO_TUNER` when the loops were registered (``--register``) but
    no tuner was ever heard on the bus (a tuner on another bus or prefix, say)."""
    stop = StopFlag()
    sim = config.sim
    by_id = {loop.loop_id: loop for loop in loops}
    session = zenoh.open(
        session_config(
            config_file=config.zenoh_config,
            mode=config.mode,
            connect=list(config.connect) or None,
            listen=list(config.listen) or None,
        )
    )
    try:
        gateway = Gateway(session, list(by_id), Keys(config.prefix), gateway_id=config.gateway_id)
        print(
            f"plant: {', '.join(by_id)} on the bus, scan {sim.scan:g} s, speed {sim.speed:g}x"
            if sim.speed
            else "plant: running as fast as possible",
            flush=True,
        )
        with ExitStack() as stack:
            writers = {
                loop_id: stack.enter_context(
                    closing(TrajectoryWriter(config.log_dir / f"{loop_id}.csv"))
                )
                for loop_id in (by_id if config.log_dir else ())
            }
            applied, ignored = run_scans(config, loops, gateway, writers, stop)
        heard = gateway.tuner_up or applied or ignored
        gateway.close()
        print(
            f"plant stopped: {applied} gain updates applied, {ignored} advisory ignored, "
            f"{gateway.inbox.invalid} invalid and {gateway.inbox.stale} stale messages dropped",
            flush=True,
        )
    finally:
        session.close()
    if not heard:
        print(
            f"plant: no tuner was heard on this bus (no gains, no liveliness token under "
            f"{config.prefix}/tuners/*): check --connect/--listen, --prefix and the tuner",
            file=sys.stderr,
            flush=True,
        )
        return EXIT_NO_TUNER if config.register else 0
    return 0


def run_scans(
    config: PlantConfig,
    loops: list[SimulatedLoop],
    gateway: Gateway,
    writers: dict[str, TrajectoryWriter],
    stop: Callable[[], bool],
) -> tuple[int, int]:
    """The scan loop; returns (gain updates applied, advisory updates ignored)."""
    sim = config.sim
    by_id = {loop.loop_id: loop for loop in loops}
    applied = ignored = 0
    progress_every = round(config.progress / sim.scan) if config.progress > 0 else 0
    last = round(sim.duration / sim.scan) if sim.duration is not None else None

    def take_gains() -> None:
        nonlocal applied, ignored
        for msg in gateway.gains():  # seq rule applied, state replies included
            if msg.mode == Mode.auto:
                by_id[msg.loop_id].apply_gains(msg.kp, msg.ki)
                applied += 1
            else:
                ignored += 1

    waiting = config.tuner_lag > 0.0
    for k in paced(sim.scan, sim.speed, stop):
        if last is not None and k >= last:
            break
        take_gains()
        samples = {}
        for loop in loops:
            scan = loop.scan()
            samples[loop.loop_id] = to_sample(scan)
            if loop.loop_id in writers:
                writers[loop.loop_id].write(scan)
            if progress_every and k % progress_every == 0:
                print(
                    f"t={scan.t:9.0f}s {loop.loop_id}: sp={scan.sp:.4g} pv={scan.pv:.4g} "
                    f"op={scan.op:.4g} kp={scan.kp:.4g} ki={scan.ki:.4g}",
                    flush=True,
                )
        gateway.publish_scan(samples)  # one batch on the gateway's key with a gateway id
        if waiting and samples:
            t = min(sample.t for sample in samples.values())
            waiting = wait_for_tuner(gateway, list(by_id), t - config.tuner_lag, take_gains, stop)
    return applied, ignored


TUNER_WAIT_S = 10.0
"""Wall seconds the plant waits for a tuner that does not catch up before it stops
waiting for the rest of the run (a tuner down must not stall the plant)."""
POLL_S = 0.01
"""Wall seconds between two state queries while waiting."""


def wait_for_tuner(
    gateway: Gateway, loop_ids: list[str], t: float, take_gains: Callable[[], None],
    stop: Callable[[], bool],
) -> bool:  # fmt: skip
    """Hold the scan loop until the tuner has accepted every loop's samples up to plant
    time ``t`` (the ``last_t`` of its state replies), asking for its state and applying
    the gains that arrive meanwhile. The pace in simulated time is then the slower of
    ``speed`` and the tuner's: on a machine too busy for the speed, the tuner's reaction
    stays a few scans in simulated time (at 120x and a tuner 4 s of wall time behind,
    the two-tank demo's first tuning from its identified model landed 8 simulated
    minutes late, next to a setpoint change). Returns False when it gave up
    (:data:`TUNER_WAIT_S`: no tuner, or one that does not catch up)."""

    def caught_up() -> bool:
        states = gateway.inbox.supervision
        seen = [states[i].last_t if i in states else None for i in loop_ids]
        return all(s is not None and s >= t for s in seen)

    if caught_up():
        return True
    deadline = time.monotonic() + TUNER_WAIT_S
    while not stop():
        gateway.query_state()
        time.sleep(POLL_S)
        take_gains()
        if caught_up():
            return True
        if time.monotonic() > deadline:
            print(
                f"plant: the tuner has not accepted the samples of t={t:g} s after "
                f"{TUNER_WAIT_S:g} s: running on without waiting for it",
                file=sys.stderr, flush=True,
            )  # fmt: skip
            return False
    return True
