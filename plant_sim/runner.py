"""The simulator's scan loop on the bus: paced in simulated time, samples out, gains in.

Every DCS scan of simulated time (``speed`` times real time, 0 for as fast as possible)
each loop publishes a :class:`~service.wire.protocol.Sample` in engineering units with
the gains in force. Gains messages whose mode is ``auto`` are applied bumplessly,
clipped to the loop's own bounds, and the samples from then on report the message's seq
as ``applied_seq`` (0 while none of the tuner's epoch is applied): gains clipped are the
tuner's to adopt, not an update still in flight. ``advisory`` ones are only counted. The
bus side follows docs/protocol.md (:mod:`service.gateways.base`).
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
from service.wire.session import join_failure, session_config


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
    try:
        session = zenoh.open(
            session_config(
                config_file=config.zenoh_config,
                mode=config.mode,
                connect=list(config.connect) or None,
                listen=list(config.listen) or None,
            )
        )
    except zenoh.ZError as exc:  # a malformed endpoint or config (2), a port in use (1)
        where = f"--listen {','.join(config.listen) or '-'} / --connect " + (
            ",".join(config.connect) or "-"
        )
        where += f" / --zenoh-config {config.zenoh_config}" if config.zenoh_config else ""
        usage, message = join_failure(exc, where)
        print(f"pitune plant: {message}", file=sys.stderr)
        return 2 if usage else 1
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
            f"{gateway.inbox.invalid} invalid, {gateway.inbox.stale} stale and "
            f"{gateway.inbox.implausible} implausible (epoch ahead) messages dropped",
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
                # reported as applied_seq from this scan's sample on: gains clipped to
                # the loop's bounds are then the tuner's to adopt, not an update in flight
                gateway.applied(msg)
                applied += 1
            else:
                ignored += 1

    pace = TunerPace(gateway, list(by_id), config.tuner_lag, take_gains, stop)
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
        if config.tuner_lag > 0.0 and samples:
            pace.hold(min(sample.t for sample in samples.values()))
    return applied, ignored


TUNER_WAIT_S = 10.0
"""Wall seconds the plant waits for a tuner that makes no progress (accepts no newer
sample) before it stops waiting (a tuner down must not stall the plant)."""
POLL_S = 0.01
"""Wall seconds between two state queries while waiting."""
RECHECK_S = 1.0
"""Wall seconds between two state queries once the plant stopped waiting: a tuner heard
making progress again is waited for again (one query a second, not a hundred)."""


class TunerPace:
    """Holds the scan loop until the tuner has accepted every loop's samples up to
    ``lag`` simulated seconds ago (the ``last_t`` of its state replies), asking for its
    state and applying the gains that arrive meanwhile. The pace in simulated time is
    then the slower of ``speed`` and the tuner's: on a machine too busy for the speed,
    the tuner's reaction stays a few scans in simulated time (at 120x and a tuner 4 s of
    wall time behind, the two-tank demo's first tuning from its identified model landed
    8 simulated minutes late, next to a setpoint change).

    A tuner that accepts no newer sample for :data:`TUNER_WAIT_S` (down, or not started
    yet) is not waited for; the plant runs on at its speed and asks once every
    :data:`RECHECK_S` whether it is back. When its replies show progress again the plant
    waits for it again: a tuner slow to start (a cold import on a loaded machine) or
    restarted is caught up with, not outrun for the rest of the run. The pace is the
    slowest loop's: a loop the tuner does not answer (not registered there, its samples
    rejected) stops the waiting, and the message names it."""

    def __init__(
        self, gateway: Gateway, loop_ids: list[str], lag: float,
        take_gains: Callable[[], None], stop: Callable[[], bool],
    ) -> None:  # fmt: skip
        self.gateway, self.loop_ids, self.lag = gateway, loop_ids, lag
        self.take_gains, self.stop = take_gains, stop
        self.waiting = True
        """False while the plant runs on without the tuner."""
        self.seen: float | None = None
        """The tuner's least accepted sample time when last looked at (progress test)."""
        self.asked = -float("inf")
        """Wall time of the last state query while not waiting."""

    def last(self) -> dict[str, float | None]:
        """Plant time of each loop's last sample the tuner accepted (None: not answered)."""
        states = self.gateway.inbox.supervision
        return {i: states[i].last_t if i in states else None for i in self.loop_ids}

    def accepted(self) -> float | None:
        """Plant time up to which the tuner has accepted every loop's samples (None: a
        loop it has not answered for)."""
        seen = self.last().values()
        return None if any(s is None for s in seen) else min(seen)

    def progressed(self) -> bool:
        """Whether the tuner accepted newer samples since last looked at (and note them)."""
        latest = self.accepted()
        if latest is None or (self.seen is not None and latest <= self.seen):
            return False
        self.seen = latest
        return True

    def hold(self, t: float) -> None:
        """Called after the samples of plant time ``t`` went out."""
        if not self.waiting:
            now = time.monotonic()
            if now - self.asked < RECHECK_S:
                return
            self.asked = now
            back = self.progressed()  # on the replies to the last query
            self.gateway.query_state()
            if not back:
                return
            self.waiting = True
            print(
                "plant: the tuner is making progress again: waiting for it",
                file=sys.stderr, flush=True,
            )  # fmt: skip
        self.wait(t - self.lag)

    def wait(self, target: float) -> None:
        """Poll until the tuner has accepted every loop's samples up to ``target``, the
        plant stops, or :data:`TUNER_WAIT_S` pass without progress (then stop waiting)."""
        deadline = time.monotonic() + TUNER_WAIT_S
        while not self.stop():
            latest = self.accepted()
            if latest is not None and latest >= target:
                return
            if self.progressed():
                deadline = time.monotonic() + TUNER_WAIT_S
            elif time.monotonic() > deadline:
                behind = [i for i, s in self.last().items() if s is None or s < target]
                print(
                    f"plant: the tuner has accepted no newer sample of {', '.join(behind)} "
                    f"for {TUNER_WAIT_S:g} s (waiting for t={target:g} s): running on "
                    "without waiting for it",
                    file=sys.stderr, flush=True,
                )  # fmt: skip
                self.waiting = False
                self.asked = time.monotonic()
                return
            self.gateway.query_state()
            time.sleep(POLL_S)
            self.take_gains()
