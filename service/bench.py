"""``pitune bench``: load benchmark of the tuner daemon over Zenoh on loopback.

The command starts a tuner daemon (``pitune tuner``) as a child process with a fresh
database, registers N loops over the REST API (``POST /loops/bulk``), then becomes the
load generator: N FOPTD plants under PI control (:class:`plant_sim.FOPTDBatch` and
:class:`plant_sim.PIBatch`, vectorised), sampled in real time at ``--rate`` per loop,
publishing their samples over Zenoh (batched ``{prefix}/samples`` messages, as a
gateway fronting many loops would, or one message per sample with ``--per-loop``) and
applying the gains the tuner sends back (bumplessly, between samples). The loops are
registered with ``gateway: "bench"``, so their gains come batched on
``{prefix}/gateways/bench/gains``; with ``--per-loop`` or ``--per-loop-gains`` they are
registered without one and get a message each on ``{prefix}/loops/{id}/gains``.

Sample clocks are spread: the loops are split into phase groups ``--tick`` apart, so
at 1 Hz and 10 ms ticks every 10 ms one hundredth of the loops is sampled, and their
RL periods differ (plant time constants are drawn from ``--tau``), so RL steps are
spread too. ``--aligned`` is the worst case: every loop is sampled at the same instant
and has the same RL period, so all N loops fall due in the same sample.

Measured over a steady window (``--duration`` seconds after ``--warmup``):

* samples published per second (generator) and accepted per second (daemon metrics);
  samples lost (published minus received once the daemon drained) and rejected, both
  over the whole run: they must be zero;
* update latency: from the wall time the generator published the sample that
  completed an RL step to the arrival of the gains message for it (matched by loop and
  the sample's plant time ``t``, which gains messages carry): p50, p99, max;
* the daemon's CPU use and RSS (``/proc``), the generator's CPU use, and the RSS per
  loop (growth from registering 1,000 to registering all N loops, divided);
* the batched inference step for N due loops, timed in this process on one thread,
  for ``agent.act`` and the daemon's :class:`service.agent.fast.FastPolicy`.

It prints a table and writes the JSON to ``benchmarks/results/``.
"""

from __future__ import annotations

import argparse
import collections
import gc
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import orjson

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
GATEWAY = "bench"
"""The gateway the loops are registered with (batched gains), unless per-loop gains."""
RING = 16
"""Sent-time stamps kept per loop (samples back in time a gains message may refer to)."""
BAR = {
    "lost": 0,
    "rejected": 0,
    "latency_p99_ms": 50.0,
    "daemon_rss_mb": 1024.0,
    "rss_per_loop_kb": 4.0,
    "inference_ms": 20.0,
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    a = parser.add_argument
    a("--loops", type=int, default=10_000, help="simulated loops (default 10000)")
    a("--rate", type=float, default=1.0, help="samples per second per loop (default 1)")
    a("--duration", type=float, default=60.0, help="measured window, seconds (default 60)")
    a("--warmup", type=float, default=10.0, help="seconds before the window (default 10)")
    a("--aligned", action="store_true", help="worst case: all loops sampled and due together")
    a("--per-loop", action="store_true",
      help="one message per sample and per gains update instead of batches")  # fmt: skip
    a("--per-loop-gains", action="store_true",
      help="batched samples, but one gains message per loop and update")  # fmt: skip
    a("--batch-size", type=int, default=2000, help="most samples per batch message")
    a("--tick", type=float, default=0.01, help="spacing of the phase groups, seconds")
    a("--tau", type=float, nargs=2, default=(5.0, 30.0), metavar=("MIN", "MAX"),
      help="range of plant time constants, seconds (RL period = 5.5 tau)")  # fmt: skip
    a("--agent-weights", default=None, help="weights file for the daemon (default: shipped)")
    a("--inference-threads", type=int, default=1, help="torch threads of the daemon")
    a("--inference-workers", type=int, default=1, help="threads stepping one large batch")
    a(
        "--inference-precision",
        choices=["auto", "float32", "bfloat16"],
        default="auto",
        help="GEMM arithmetic of the daemon and of the inference timing",
    )
    a("--snapshot-interval", type=float, default=30.0, help="daemon snapshot period, s")
    a("--memory-probe", type=int, default=1000,
      help="register this many loops first to measure RSS per loop (0: skip)")  # fmt: skip
    a("--pin", default=None, metavar="DAEMON:GEN",
      help="pin daemon and generator to CPU lists, e.g. 0:1")  # fmt: skip
    a("--seed", type=int, default=0)
    a("--out", type=Path, default=RESULTS, help="results directory")
    a("--no-inference-bench", action="store_true", help="skip the in-process inference timing")
    a("--daemon-log", type=Path, default=None, help="keep the daemon's log here")
    a("--trace", type=Path, default=None,
      help="write the update latencies of the window to this CSV")  # fmt: skip


# -- the daemon ---------------------------------------------------------------------------
@dataclass
class Daemon:
    proc: subprocess.Popen
    api: str
    endpoint: str
    log: Path

    def cpu_seconds(self) -> float:
        fields = Path(f"/proc/{self.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def rss_mb(self) -> float:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
        return math.nan

    def stop(self) -> int | None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        return self.proc.returncode


def start_daemon(args: argparse.Namespace, workdir: Path) -> Daemon:
    from service.wire.session import free_port

    api_port, zenoh_port = free_port(), free_port()
    endpoint = f"tcp/127.0.0.1:{zenoh_port}"
    log = args.daemon_log or workdir / "daemon.log"
    cmd = [
        sys.executable, "-m", "service.cli", "tuner",
        "--api-port", str(api_port), "--listen", endpoint, "--db", str(workdir / "bench.db"),
        "--instance-id", "bench", "--log-level", "warning",
        "--snapshot-interval", str(args.snapshot_interval),
        "--inference-threads", str(args.inference_threads),
        "--inference-workers", str(args.inference_workers),
        "--inference-precision", args.inference_precision,
    ]  # fmt: skip
    if args.agent_weights:
        cmd += ["--agent-weights", args.agent_weights]
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
    }
    env.pop("PITUNE_API_TOKEN", None)
    env.pop("PITUNE_CONFIG", None)
    with open(log, "wb") as out:
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)
    daemon = Daemon(proc, f"http://127.0.0.1:{api_port}", endpoint, log)
    if args.pin:
        os.sched_setaffinity(proc.pid, _cpus(args.pin.split(":")[0]))
    return daemon


def _cpus(spec: str) -> set[int]:
    return {int(c) for c in spec.split(",") if c}


def wait_ready(client, daemon: Daemon, timeout: float = 60.0) -> None:
    import httpx

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if daemon.proc.poll() is not None:
            raise RuntimeError(f"daemon exited ({daemon.proc.returncode}); see {daemon.log}")
        try:
            if client.get(f"{daemon.api}/readyz").status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.1)
    raise RuntimeError(f"daemon not ready after {timeout} s; see {daemon.log}")


def scrape(client, daemon: Daemon) -> dict[str, float]:
    """The daemon's metrics as {name{labels}: value}."""
    from prometheus_client.parser import text_string_to_metric_families

    text = client.get(f"{daemon.api}/metrics").text
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            labels = ",".join(f"{k}={v}" for k, v in sorted(s.labels.items()))
            out[f"{s.name}{{{labels}}}" if labels else s.name] = s.value
    return out


def system_busy() -> tuple[float, float]:
    """(busy, total) CPU seconds of the whole machine so far, from /proc/stat."""
    fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = fields[3] + fields[4]  # idle + iowait
    tick = os.sysconf("SC_CLK_TCK")
    return (sum(fields[:8]) - idle) / tick, sum(fields[:8]) / tick


def rejected(metrics: dict[str, float]) -> float:
    return sum(v for k, v in metrics.items() if k.startswith("pitune_samples_rejected_total{"))


# -- the simulated loops ------------------------------------------------------------------
@dataclass
class Group:
    """Loops sampled at the same instants (one phase of the sample clock)."""

    offset: float
    index: np.ndarray
    """Global loop indices."""
    plant: object
    pi: object
    sp_half: np.ndarray
    sp_phase: np.ndarray
    ids: list[str]
    sent: np.ndarray
    """(n, RING) monotonic publish time of sample k at column k % RING."""
    sent_k: np.ndarray
    pending: list = field(default_factory=list)


class Fleet:
    """N FOPTD plants under PI control in phase groups; gains applied bumplessly."""

    def __init__(self, args: argparse.Namespace) -> None:
        from plant_sim import FOPTDBatch, PIBatch
        from plant_sim.tunings import simc_paper, to_parallel

        n, rng = args.loops, np.random.default_rng(args.seed)
        self.n, self.period = n, 1.0 / args.rate
        self.ids = [f"L{i:05d}" for i in range(n)]
        gateway = {} if args.per_loop or args.per_loop_gains else {"gateway": GATEWAY}
        self.where = {}
        lo, hi = args.tau
        if args.aligned:
            tau = np.full(n, math.sqrt(lo * hi))
        else:
            tau = np.exp(rng.uniform(math.log(lo), math.log(hi), n))
        K = np.exp(rng.uniform(math.log(0.5), math.log(2.0), n))
        theta = tau * rng.uniform(0.1, 0.5, n)
        kp, ki = to_parallel(*simc_paper(K, tau, theta))
        detune = np.exp(rng.uniform(math.log(0.3), math.log(3.0), (2, n)))
        self.kp0, self.ki0 = kp * detune[0], ki * detune[1]
        self.registrations = [
            {
                "id": self.ids[i],
                "kp": float(self.kp0[i]),
                "ki": float(self.ki0[i]),
                "sample_period_s": self.period,
                "scaling": {
                    "k_hat": float(K[i] * math.exp(rng.normal(0.0, 0.2))),
                    "tau_hat": float(tau[i]),
                    "pv_scale": 1.0,
                },
                # every due loop is stepped, whatever its setpoint does: the worst case
                "guard": {"excitation_periods": 0.0},
                **gateway,
            }
            for i in range(n)
        ]
        n_groups = 1 if args.aligned else max(1, min(n, round(self.period / args.tick)))
        self.groups: list[Group] = []
        for g in range(n_groups):
            idx = np.arange(g, n, n_groups)
            plant = FOPTDBatch(K[idx], tau[idx], theta[idx], dt=self.period, noise_std=0.01,
                               seed=rng.integers(1 << 31))  # fmt: skip
            plant.reset(0.0)
            pi = PIBatch(self.kp0[idx], self.ki0[idx], dt=self.period)
            pi.initialise(0.0)
            self.groups.append(
                Group(
                    offset=g * self.period / n_groups,
                    index=idx,
                    plant=plant,
                    pi=pi,
                    sp_half=rng.uniform(20.0, 60.0, idx.size),
                    sp_phase=rng.uniform(0.0, 120.0, idx.size),
                    ids=[self.ids[i] for i in idx],
                    sent=np.full((idx.size, RING), np.nan),
                    sent_k=np.full((idx.size, RING), -1, np.int64),
                )
            )
            for j, i in enumerate(idx):
                self.where[self.ids[i]] = (g, j)

    def scan(self, g: int, k: int, t0: float) -> tuple[float, list[dict]]:
        """Sample group ``g`` at its ``k``-th instant: plant time and the samples."""
        grp = self.groups[g]
        self._apply(grp)
        t = t0 + k * self.period + grp.offset
        sp = np.where(((t + grp.sp_phase) // grp.sp_half) % 2 == 0, 1.0, -1.0)
        pv = grp.plant.measure()
        u = grp.pi.step(sp - pv)
        grp.plant.step(u)
        ids, sps, pvs = grp.ids, sp.tolist(), pv.tolist()
        kps, kis = grp.pi.kp.tolist(), grp.pi.ki.tolist()
        samples = [
            {"loop_id": ids[j], "t": t, "sp": sps[j], "pv": pvs[j], "kp": kps[j], "ki": kis[j]}
            for j in range(len(ids))
        ]
        return t, samples

    def stamp(self, g: int, k: int, wall: float) -> None:
        grp = self.groups[g]
        grp.sent[:, k % RING] = wall
        grp.sent_k[:, k % RING] = k

    def sent_time(self, loop_id: str, t: float, t0: float) -> float:
        """Monotonic publish time of the loop's sample at plant time ``t`` (NaN: unknown)."""
        g, j = self.where[loop_id]
        grp = self.groups[g]
        k = round((t - t0 - grp.offset) / self.period)
        if grp.sent_k[j, k % RING] != k:
            return math.nan
        return float(grp.sent[j, k % RING])

    def offer(self, loop_id: str, kp: float, ki: float) -> None:
        g, j = self.where[loop_id]
        self.groups[g].pending.append((j, kp, ki))

    @staticmethod
    def _apply(grp: Group) -> None:
        if not grp.pending:
            return
        j, kp, ki = (np.asarray(v) for v in zip(*grp.pending, strict=True))
        grp.pending.clear()
        pi = grp.pi
        pi.integral[j] -= (kp - pi.kp[j]) * pi.e_last[j]  # bumpless, as set_gains
        pi.kp[j], pi.ki[j] = kp, ki


# -- the run ------------------------------------------------------------------------------
@dataclass
class Window:
    start: float
    end: float


def register(client, daemon: Daemon, bodies: list[dict], chunk: int = 5000) -> float:
    started = time.perf_counter()
    for i in range(0, len(bodies), chunk):
        r = client.post(f"{daemon.api}/loops/bulk", json=bodies[i : i + chunk], timeout=300)
        if r.status_code != 201:
            raise RuntimeError(f"bulk registration failed: {r.status_code} {r.text[:500]}")
    return time.perf_counter() - started


def settle_rss(daemon: Daemon, seconds: float = 2.0) -> float:
    time.sleep(seconds)
    return daemon.rss_mb()


def inference_bench(args: argparse.Namespace, n: int) -> dict:
    """Time one batched step of ``n`` due loops on one torch thread (min and median)."""
    import torch

    from service.agent import load_agent, untrained_agent
    from service.agent.fast import FastPolicy

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        if args.agent_weights == "untrained":
            agent = untrained_agent(0)
        else:
            agent = load_agent(args.agent_weights) if args.agent_weights else load_agent()
        rng = np.random.default_rng(1)
        obs = np.column_stack(
            [np.exp(rng.normal(0, 1, (n, 2))), rng.normal(0, 0.5, n), rng.normal(0, 2, n)]
        )
        state = rng.normal(0, 0.3, (n, agent.cfg.layers, agent.cfg.hidden)).astype(np.float32)
        gamma = np.full(n, 0.99)
        fast = FastPolicy(agent, workers=args.inference_workers, precision=args.inference_precision)
        out = {
            "loops": n,
            "torch_threads": 1,
            "workers": args.inference_workers,
            "precision": fast.precision,
        }
        for name, fn in (
            ("agent_act", lambda: agent.act(obs, state, gamma)),
            ("fast_policy", lambda: fast.step_inplace(obs, state.copy(), gamma)),
        ):
            times = []
            for _ in range(21):  # the box is noisy: a median of many
                started = time.perf_counter()
                fn()
                times.append(time.perf_counter() - started)
            out[f"{name}_ms_min"] = 1e3 * min(times)
            out[f"{name}_ms_median"] = 1e3 * float(np.median(times))
        return out
    finally:
        torch.set_num_threads(threads)


def run(args: argparse.Namespace) -> int:
    import httpx

    if args.loops < 1 or args.rate <= 0 or args.duration <= 0 or args.warmup < 0:
        print("pitune bench: --loops, --rate, --duration must be positive", file=sys.stderr)
        return 2
    machine = machine_info()
    inference = None if args.no_inference_bench else inference_bench(args, args.loops)
    fleet = Fleet(args)
    with tempfile.TemporaryDirectory(prefix="pitune-bench-") as tmp:
        daemon = start_daemon(args, Path(tmp))
        try:
            with httpx.Client(timeout=30) as client:
                wait_ready(client, daemon)
                result = drive(args, fleet, daemon, client)
        finally:
            code = daemon.stop()
        result["daemon_exit"] = code
    result.update(config=_config(args), machine=machine, inference=inference)
    result["bar"] = judge(args, result)
    path = write(args, result)
    print(table(result))
    print(f"\nwritten to {path}")
    lost_or_rejected = result["samples"]["lost"] or result["samples"]["rejected"]
    return 1 if lost_or_rejected else 0


def drive(args: argparse.Namespace, fleet: Fleet, daemon: Daemon, client) -> dict:
    """Register the loops, play them in real time, measure."""
    import zenoh

    from service.wire.protocol import Keys
    from service.wire.session import session_config

    memory = {"rss_idle_mb": daemon.rss_mb()}
    probe = args.memory_probe if 0 < args.memory_probe < fleet.n else 0
    if probe:
        memory["register_s_first"] = register(client, daemon, fleet.registrations[:probe])
        memory[f"rss_{probe}_loops_mb"] = settle_rss(daemon)
    memory["register_s"] = register(client, daemon, fleet.registrations[probe:])
    memory[f"rss_{fleet.n}_loops_mb"] = settle_rss(daemon)
    if probe:
        grown = memory[f"rss_{fleet.n}_loops_mb"] - memory[f"rss_{probe}_loops_mb"]
        memory["rss_per_loop_kb"] = 1024.0 * grown / (fleet.n - probe)
    if args.pin:
        os.sched_setaffinity(0, _cpus(args.pin.split(":")[1]))

    keys = Keys()
    session = zenoh.open(session_config(mode="peer", connect=[daemon.endpoint]))
    inbox: collections.deque = collections.deque()
    try:
        per_loop_gains = args.per_loop or args.per_loop_gains
        sub = session.declare_subscriber(
            keys.all_gains if per_loop_gains else keys.gateway_gains(GATEWAY),
            lambda s: inbox.append((time.monotonic(), s.payload.to_bytes())),
        )
        _wait_for_tuner(session, keys)
        gc.freeze()  # no full collections of the imported modules while timing
        try:
            return play(args, fleet, daemon, client, session, keys, inbox, memory)
        finally:
            sub.undeclare()
    finally:
        session.close()


def _wait_for_tuner(session, keys, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if list(session.liveliness().get(keys.all_tuners, timeout=1.0)):
            time.sleep(0.2)  # let the subscriptions propagate
            return
    raise RuntimeError("no tuner liveliness token on the bus")


def play(args, fleet: Fleet, daemon: Daemon, client, session, keys, inbox, memory) -> dict:
    import zenoh

    period, n_groups = fleet.period, len(fleet.groups)
    t0 = 1000.0  # plant time of the first sample
    start = time.monotonic() + 0.2
    window = Window(start + args.warmup, start + args.warmup + args.duration)
    total = args.warmup + args.duration
    latencies: list[float] = []
    stats = collections.Counter()
    stats.trace = []
    late_max = 0.0
    rss_max, next_rss = 0.0, 0.0
    cpu0 = gen0 = m0 = None
    # Samples must not be lost: block rather than drop when the transport is congested
    # (Zenoh's default for puts is to drop), as a gateway should.
    block = zenoh.CongestionControl.BLOCK

    def publish(key: str, payload: bytes) -> None:
        session.put(key, payload, congestion_control=block)

    batch_key = keys.batch
    m = 0
    while True:
        g, k = m % n_groups, m // n_groups
        due = start + k * period + fleet.groups[g].offset
        if due - start >= total:
            break
        now = time.monotonic()
        if cpu0 is None and now >= window.start:
            cpu0, gen0, m0 = daemon.cpu_seconds(), time.process_time(), scrape(client, daemon)
            sys0 = system_busy()
            wall0 = time.monotonic()
        if now >= next_rss:
            rss = daemon.rss_mb()
            if window.start <= now < window.end:
                rss_max = max(rss_max, rss)
            next_rss = now + 1.0
        _drain(inbox, fleet, t0, window, latencies, stats)
        now = time.monotonic()
        if due > now:
            time.sleep(due - now)
        else:
            late_max = max(late_max, now - due)
        t, samples = fleet.scan(g, k, t0)
        sent = time.monotonic()
        if args.per_loop:
            for s in samples:
                loop_id = s.pop("loop_id")
                publish(keys.sample(loop_id), orjson.dumps(s))
        else:
            for i in range(0, len(samples), args.batch_size):
                publish(
                    batch_key, orjson.dumps({"v": 1, "samples": samples[i : i + args.batch_size]})
                )
        fleet.stamp(g, k, sent)
        stats["published"] += len(samples)
        if window.start <= sent < window.end:
            stats["published_window"] += len(samples)
        m += 1
    wall1 = time.monotonic()
    cpu1, gen1, m1 = daemon.cpu_seconds(), time.process_time(), scrape(client, daemon)
    sys1 = system_busy()
    rss_end = daemon.rss_mb()
    # drain: the daemon should have received everything; the last gains arrive shortly
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        m2 = scrape(client, daemon)
        if m2["pitune_samples_received_total"] >= stats["published"]:
            break
        time.sleep(0.1)
    time.sleep(1.0)
    _drain(inbox, fleet, t0, window, latencies, stats)
    m2 = scrape(client, daemon)

    span = wall1 - wall0
    if args.trace:
        with open(args.trace, "w") as out:
            out.write("t_s,loop_id,latency_ms\n")
            out.writelines(f"{t:.3f},{i},{1e3 * d:.2f}\n" for t, i, d in stats.trace)
    lat = np.asarray(latencies) * 1e3
    received = m2["pitune_samples_received_total"]
    n_rejected = rejected(m2)
    accepted_window = (m1["pitune_samples_received_total"] - rejected(m1)) - (
        m0["pitune_samples_received_total"] - rejected(m0)
    )
    inf_count = (
        m1["pitune_inference_batch_seconds_count"] - m0["pitune_inference_batch_seconds_count"]
    )
    inf_sum = m1["pitune_inference_batch_seconds_sum"] - m0["pitune_inference_batch_seconds_sum"]
    return {
        "samples": {
            "published": stats["published"],
            "received": received,
            "rejected": n_rejected,
            "rejected_by_reason": {
                k.split("reason=")[1].rstrip("}"): v
                for k, v in m2.items()
                if k.startswith("pitune_samples_rejected_total{") and v
            },
            "lost": stats["published"] - received,
            "published_per_s": stats["published_window"] / args.duration,
            "accepted_per_s": accepted_window / span,
        },
        "updates": {
            "gains_received": stats["gains"],
            "gains_in_window": len(latencies),
            "unmatched": stats["unmatched"],
            "per_s": len(latencies) / args.duration,
            "latency_ms": _percentiles(lat),
            "inference_calls": inf_count,
            "inference_mean_ms": 1e3 * inf_sum / inf_count if inf_count else None,
            "inference_loops_mean": (
                (m1["pitune_inference_batch_loops_sum"] - m0["pitune_inference_batch_loops_sum"])
                / inf_count
                if inf_count
                else None
            ),
        },
        "daemon": {
            "cpu_percent": 100.0 * (cpu1 - cpu0) / span,
            "rss_max_mb": rss_max,
            "rss_end_mb": rss_end,
            **memory,
        },
        "generator": {
            "cpu_percent": 100.0 * (gen1 - gen0) / span,
            "late_max_ms": 1e3 * late_max,
        },
        "load_average": {"end": list(os.getloadavg())},
        "machine_cpu": {
            # all CPUs together, in "% of one core" like the per-process figures
            "busy_percent": 100.0 * (sys1[0] - sys0[0]) / span,
            "others_percent": 100.0 * ((sys1[0] - sys0[0]) - (cpu1 - cpu0) - (gen1 - gen0)) / span,
            "capacity_percent": 100.0 * (sys1[1] - sys0[1]) / span,
        },
    }


def _drain(inbox, fleet: Fleet, t0: float, window: Window, latencies: list, stats) -> None:
    while inbox:
        received, payload = inbox.popleft()
        msg = orjson.loads(payload)
        for gains in msg.get("gains", [msg]):  # a GainsBatch, or one GainsMessage
            _take(gains, received, fleet, t0, window, latencies, stats)


def _take(msg: dict, received: float, fleet: Fleet, t0: float, window: Window, latencies, stats):
    stats["gains"] += 1
    if msg.get("reason", "agent") == "agent":
        sent = fleet.sent_time(msg["loop_id"], msg["t"], t0)
        if math.isnan(sent):
            stats["unmatched"] += 1
        elif window.start <= sent < window.end:
            latencies.append(received - sent)
            stats.trace.append((sent - window.start, msg["loop_id"], received - sent))
        if msg["mode"] == "auto":
            fleet.offer(msg["loop_id"], msg["kp"], msg["ki"])


def _percentiles(lat_ms: np.ndarray) -> dict:
    if not lat_ms.size:
        return {"p50": None, "p99": None, "max": None, "mean": None}
    return {
        "p50": float(np.percentile(lat_ms, 50)),
        "p99": float(np.percentile(lat_ms, 99)),
        "max": float(lat_ms.max()),
        "mean": float(lat_ms.mean()),
    }


# -- reporting ----------------------------------------------------------------------------
def machine_info() -> dict:
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    return {
        "cpu": model,
        "cpus": os.cpu_count(),
        "memory_gb": round(mem, 1),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "load_average_start": list(os.getloadavg()),
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def _config(args: argparse.Namespace) -> dict:
    cfg = {k: v for k, v in vars(args).items() if k not in ("command",)}
    return json.loads(json.dumps(cfg, default=str))


def judge(args: argparse.Namespace, r: dict) -> dict:
    """Each line of the issue's bar: value, limit, met (None when not measured)."""
    lat = r["updates"]["latency_ms"]["p99"]
    inf = r.get("inference") or {}

    def line(value, limit, met):
        return {"value": value, "limit": limit, "met": None if value is None else bool(met)}

    per_loop = r["daemon"].get("rss_per_loop_kb")
    fast = inf.get("fast_policy_ms_median")
    return {
        "samples_lost": line(r["samples"]["lost"], 0, r["samples"]["lost"] == 0),
        "samples_rejected": line(r["samples"]["rejected"], 0, r["samples"]["rejected"] == 0),
        "latency_p99_ms": line(lat, BAR["latency_p99_ms"], lat is not None and lat < 50.0),
        "daemon_rss_mb": line(r["daemon"]["rss_max_mb"], 1024.0, r["daemon"]["rss_max_mb"] < 1024),
        "rss_per_loop_kb": line(per_loop, 4.0, per_loop is not None and per_loop < 4.0),
        "inference_ms": line(fast, 20.0, fast is not None and fast < 20.0),
    }


def write(args: argparse.Namespace, result: dict) -> Path:
    args.out.mkdir(parents=True, exist_ok=True)
    tag = f"{args.loops}x{args.rate:g}hz{'-aligned' if args.aligned else ''}"
    tag += "-perloop" if args.per_loop else "-perloopgains" if args.per_loop_gains else ""
    path = args.out / f"{time.strftime('%Y%m%d-%H%M%S')}-{tag}.json"
    path.write_text(json.dumps(result, indent=2, default=float) + "\n")
    return path


def _f(value, fmt: str = "{:.1f}") -> str:
    return "n/a" if value is None else fmt.format(value)


def table(r: dict) -> str:
    c, s, u, d, g = r["config"], r["samples"], r["updates"], r["daemon"], r["generator"]
    lat, mach, inf = u["latency_ms"], r["machine"], r.get("inference") or {}
    mode = "aligned (worst case)" if c["aligned"] else "spread"
    if c["per_loop"]:
        msg = "per-loop messages"
    else:
        gains = "per-loop gains" if c.get("per_loop_gains") else "batched gains"
        msg = f"batches of <= {c['batch_size']}, {gains}"
    rows = [
        ("loops x rate", f"{c['loops']} x {c['rate']:g}/s, {mode}, {msg}"),
        ("window", f"{c['duration']:g} s after {c['warmup']:g} s warm-up"),
        ("samples published / accepted",
         f"{s['published_per_s']:.0f}/s / {s['accepted_per_s']:.0f}/s"),
        ("samples lost / rejected (run)",
         f"{s['lost']:.0f} / {s['rejected']:.0f} of {s['published']}"),
        ("gains in window",
         f"{u['gains_in_window']} ({u['per_s']:.1f}/s), {u['unmatched']} unmatched"),
        ("update latency p50 / p99 / max",
         f"{_f(lat['p50'])} / {_f(lat['p99'])} / {_f(lat['max'])} ms"),
        ("daemon batch step (mean)", f"{_f(u['inference_mean_ms'], '{:.2f}')} ms for "
                                     f"{_f(u['inference_loops_mean'])} loops on average"),
        ("daemon CPU", f"{d['cpu_percent']:.0f} % of one core"),
        ("daemon RSS max / end", f"{d['rss_max_mb']:.0f} / {d['rss_end_mb']:.0f} MB"),
        ("RSS per loop", f"{_f(d.get('rss_per_loop_kb'), '{:.2f}')} KB"),
        ("generator CPU / worst lag", f"{g['cpu_percent']:.0f} % / {g['late_max_ms']:.1f} ms"),
        ("other processes' CPU", f"{r['machine_cpu']['others_percent']:.0f} % (machine "
                                 f"{r['machine_cpu']['busy_percent']:.0f} % busy of "
                                 f"{r['machine_cpu']['capacity_percent']:.0f} %)"),
    ]  # fmt: skip
    if inf:
        rows.append(
            (
                f"inference, {inf['loops']} due loops",
                f"FastPolicy {inf['fast_policy_ms_median']:.1f} ms (min "
                f"{inf['fast_policy_ms_min']:.1f}), {inf.get('precision', 'float32')}, "
                f"{inf['workers']} worker(s); agent.act {inf['agent_act_ms_median']:.1f} ms",
            )
        )
    rows += [
        ("machine", f"{mach['cpu']}, {mach['cpus']} CPUs, {mach['memory_gb']} GB"),
        ("load average start / end", f"{_load(mach['load_average_start'])} / "
                                     f"{_load(r['load_average']['end'])}"),
    ]  # fmt: skip
    width = max(len(k) for k, _ in rows)
    lines = [f"{k:<{width}}  {v}" for k, v in rows]
    lines.append("")
    lines.append("bar:")
    for name, b in r["bar"].items():
        mark = {True: "met", False: "NOT MET", None: "not measured"}[b["met"]]
        lines.append(f"  {name:<18} {_f(b['value'], '{:.2f}'):>10}  limit {b['limit']:<7} {mark}")
    return "\n".join(lines)


def _load(values: list[float]) -> str:
    return " ".join(f"{v:.2f}" for v in values)
