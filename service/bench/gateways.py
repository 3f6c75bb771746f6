"""The load of ``pitune bench --instances N``: simulated gateways in their own processes.

One Python process cannot produce 300,000 samples/s as dicts through ``orjson`` (one
process reached 117,500/s), and a plant's many gateways are many hosts anyway. So the
gateways are split over ``--generators`` processes (default: one per instance), each
with its own Zenoh session connected to every member, and each sample batch is encoded
once, before the run: per gateway and phase group, two payloads (error +0.5 and -0.5,
flipping every 4 samples as :class:`service.bench.cluster.Load` does) with the plant time
``t`` left as a placeholder that each publish fills in (one ``bytes.replace``). Batches
go on each gateway's own samples key (protocol revision 4) with
``CongestionControl.BLOCK``: in a cluster Zenoh routes a gateway's batches to the member
owning it only.

What is not simulated here is the plant: the samples carry ``e`` only (no ``kp``/``ki``,
so the tuner assumes its ``auto`` gains applied), not a FOPTD response to the gains as in
:class:`service.bench.fleet.Fleet`. The tuner's cost per sample and per step does not
depend on the values (every due loop is stepped: the registrations turn the excitation
gate off). Each process measures the update latency of its gateways' loops as
:mod:`service.bench.load` does (from the publish of the sample that completed an RL step
to the arrival of its gains, matched by loop and plant time ``t``), over the same
window, and hands its numbers back through a pipe.
"""

from __future__ import annotations

import collections
import multiprocessing as mp
import time
from dataclasses import dataclass

import numpy as np
import orjson
import zenoh

from service.wire.protocol import Keys
from service.wire.session import session_config

RING = 16
"""Publish times kept per phase group (samples back in time a gains message may refer to)."""
PLACEHOLDER = b"@T@"
SIGN_EVERY = 4
"""Samples between sign flips of the error (every loop's setpoint steps)."""


@dataclass(frozen=True)
class Plan:
    """What one generator process plays."""

    gateways: dict[str, list[str]]
    """Gateway -> its loop ids."""
    endpoints: list[str]
    period: float
    groups: int
    """Phase groups of the sample clock (``period / tick``)."""
    batch_size: int
    columns: bool
    """Batches as :class:`~service.wire.protocol.SampleColumns` (else SampleBatch rows)."""
    window: tuple[float, float]
    """Start and end of the measured window, seconds after the start."""
    end: float
    """Seconds after the start after which nothing is published (inf: until stopped)."""
    t0: float
    """Plant time of the first samples."""


def plans(gateways: dict[str, list[str]], processes: int, **common) -> list[Plan]:
    """The gateways dealt round-robin to ``processes`` plans."""
    names = sorted(gateways)
    return [
        Plan(gateways={g: gateways[g] for g in names[p::processes]}, **common)
        for p in range(processes)
        if names[p::processes]
    ]


def _payloads(plan: Plan) -> list[list[tuple[str, bytes, bytes]]]:
    """Per phase group: (key, payload with e=+0.5, payload with e=-0.5) of every batch."""
    keys = Keys()
    out: list[list[tuple[str, bytes, bytes]]] = [[] for _ in range(plan.groups)]
    for gateway, ids in plan.gateways.items():
        key = keys.gateway_samples(gateway)
        for g in range(plan.groups):
            mine = ids[g :: plan.groups]
            for i in range(0, len(mine), plan.batch_size):
                chunk = mine[i : i + plan.batch_size]
                encode = _columns if plan.columns else _rows
                out[g].append((key, encode(chunk, b"0.5"), encode(chunk, b"-0.5")))
    return out


def _rows(ids: list[str], e: bytes) -> bytes:
    """A SampleBatch of ``ids``, each with error ``e`` and the time :data:`PLACEHOLDER`."""
    samples = (b'{"loop_id":"%s","t":%s,"e":%s}' % (x.encode(), PLACEHOLDER, e) for x in ids)
    return b'{"v":1,"samples":[' + b",".join(samples) + b"]}"


def _columns(ids: list[str], e: bytes) -> bytes:
    """The same samples as :func:`_rows`, as SampleColumns."""
    n = len(ids)
    return b'{"v":1,"columns":{"loop_id":%s,"t":[%s],"e":[%s]}}' % (
        orjson.dumps(ids),
        b",".join([PLACEHOLDER] * n),
        b",".join([e] * n),
    )


class _Latencies:
    """Gains heard -> update latencies of the samples that caused them."""

    def __init__(self, plan: Plan) -> None:
        self.plan = plan
        self.group = {
            loop_id: j % plan.groups
            for ids in plan.gateways.values()
            for j, loop_id in enumerate(ids)
        }
        """Loop id -> its phase group (a gateway's j-th loop is in group j % groups)."""
        self.sent = np.full((plan.groups, RING), np.nan)
        self.sent_k = np.full((plan.groups, RING), -1, np.int64)
        self.inbox: collections.deque = collections.deque()
        self.values: list[float] = []
        self.trace: list[tuple[float, str]] = []
        """(publish time after the window's start, loop id) of each of :attr:`values`."""
        self.gains = self.unmatched = 0

    def on_gains(self, sample: zenoh.Sample) -> None:
        self.inbox.append((time.monotonic(), sample.payload.to_bytes()))

    def stamp(self, g: int, k: int, wall: float) -> None:
        self.sent[g, k % RING] = wall
        self.sent_k[g, k % RING] = k

    def drain(self, lo: float, hi: float) -> None:
        """Latencies of the gains heard, for samples sent between ``lo`` and ``hi``."""
        plan = self.plan
        while self.inbox:
            received, payload = self.inbox.popleft()
            for msg in orjson.loads(payload)["gains"]:
                self.gains += 1
                if msg.get("reason", "agent") != "agent":
                    continue
                g = self.group[msg["loop_id"]]
                k = round((msg["t"] - plan.t0 - g * plan.period / plan.groups) / plan.period)
                if self.sent_k[g, k % RING] != k:
                    self.unmatched += 1
                    continue
                sent = self.sent[g, k % RING]
                if lo <= sent < hi:
                    self.values.append(received - sent)
                    self.trace.append((sent - lo, msg["loop_id"]))


def _play(plan: Plan, pipe, stop) -> None:
    """The child process: pre-encode, say ready, take the start time (monotonic: the
    machine's clock, shared by the processes), publish until ``plan.end`` or ``stop``,
    then send the numbers back."""
    payloads = _payloads(plan)
    per_group = [
        sum(len(ids[g :: plan.groups]) for ids in plan.gateways.values())
        for g in range(plan.groups)
    ]
    session = zenoh.open(session_config(mode="peer", connect=plan.endpoints))
    latencies = _Latencies(plan)
    subs = [
        session.declare_subscriber(Keys().gateway_gains(g), latencies.on_gains)
        for g in plan.gateways
    ]
    block = zenoh.CongestionControl.BLOCK
    published = published_window = 0
    late_max = 0.0
    cpu = [None, None]
    try:
        pipe.send("ready")
        start = pipe.recv()
        lo, hi = (start + w for w in plan.window)
        m = 0
        while not stop.is_set():
            g, k = m % plan.groups, m // plan.groups
            due = start + k * plan.period + g * plan.period / plan.groups
            if due >= start + plan.end:
                break
            latencies.drain(lo, hi)
            now = time.monotonic()
            if cpu[0] is None and now >= lo:
                cpu[0] = time.process_time()
            if cpu[1] is None and now >= hi:
                cpu[1] = time.process_time()
            if due > now:
                time.sleep(due - now)
            else:
                late_max = max(late_max, now - due)
            t = b"%.3f" % (plan.t0 + k * plan.period + g * plan.period / plan.groups)
            sign = (k // SIGN_EVERY) % 2
            sent = time.monotonic()
            for key, plus, minus in payloads[g]:
                session.put(key, (minus if sign else plus).replace(PLACEHOLDER, t),
                            congestion_control=block)  # fmt: skip
            latencies.stamp(g, k, sent)
            published += per_group[g]
            if lo <= sent < hi:
                published_window += per_group[g]
            m += 1
        deadline = time.monotonic() + 3.0  # the last gains of the window
        while time.monotonic() < deadline and not stop.is_set():
            latencies.drain(lo, hi)
            time.sleep(0.05)
        latencies.drain(lo, hi)
    finally:
        for sub in subs:
            sub.undeclare()
        session.close()
    span_cpu = (cpu[1] if cpu[1] is not None else time.process_time()) - (cpu[0] or 0.0)
    pipe.send(
        {
            "published": published,
            "published_window": published_window,
            "latencies": np.asarray(latencies.values, np.float64).tobytes(),
            "trace": latencies.trace,
            "gains": latencies.gains,
            "unmatched": latencies.unmatched,
            "cpu_s": span_cpu,
            "late_max_s": late_max,
        }
    )


class Generators:
    """The generator processes of a list of plans (spawned: no Zenoh state is forked)."""

    def __init__(self, plans: list[Plan]) -> None:
        ctx = mp.get_context("spawn")
        self.stop = ctx.Event()
        self.pipes, self.procs = [], []
        for plan in plans:
            here, there = ctx.Pipe()
            self.pipes.append(here)
            self.procs.append(ctx.Process(target=_play, args=(plan, there, self.stop)))

    def start(self, timeout: float = 120.0) -> Generators:
        """Start every process and wait until each has encoded its batches and opened its
        session (before the plans' start time, or its first samples are late)."""
        for proc in self.procs:
            proc.start()
        for pipe in self.pipes:
            if not pipe.poll(timeout) or pipe.recv() != "ready":
                raise RuntimeError("a load generator process did not start")
        return self

    def go(self, lead: float = 0.5) -> float:
        """Start publishing ``lead`` seconds from now; that monotonic start time."""
        start = time.monotonic() + lead
        for pipe in self.pipes:
            pipe.send(start)
        return start

    def results(self, timeout: float) -> dict:
        """Wait for the processes (their plans' end, or :meth:`halt`); their numbers summed
        (latencies in seconds as one array)."""
        parts = []
        for pipe, proc in zip(self.pipes, self.procs, strict=True):
            if not pipe.poll(timeout):
                raise RuntimeError("a load generator process did not report")
            parts.append(pipe.recv())
            proc.join(10.0)
        total = {k: sum(p[k] for p in parts) for k in ("published", "published_window",
                                                        "gains", "unmatched", "cpu_s")}  # fmt: skip
        total["late_max_s"] = max((p["late_max_s"] for p in parts), default=0.0)
        total["latencies"] = np.concatenate(
            [np.frombuffer(p["latencies"], np.float64) for p in parts] or [np.zeros(0)]
        )
        total["trace"] = [
            (t, loop_id, d)
            for p in parts
            for (t, loop_id), d in zip(p["trace"], np.frombuffer(p["latencies"]), strict=True)
        ]
        return total

    def halt(self) -> None:
        self.stop.set()

    def kill(self) -> None:
        """Stop everything still running (an error path)."""
        self.stop.set()
        for proc in self.procs:
            proc.join(5.0)
            if proc.is_alive():
                proc.kill()
