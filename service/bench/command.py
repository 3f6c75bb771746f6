"""``pitune bench``: the command line. The options are read into a
:class:`~service.bench.config.BenchConfig` once; the run starts the tuner daemon as a
child process (:class:`service.procs.TunerProcess`, fresh database), drives it
(:mod:`service.bench.load`) and reports (:mod:`service.bench.report`)."""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import fields
from pathlib import Path

import httpx

from service.bench import monitor_ab, retention, scaleout
from service.bench.config import BenchConfig
from service.bench.fleet import Fleet
from service.bench.load import drive
from service.bench.probes import machine_info
from service.bench.report import judge, table, write
from service.engine.config import guard_option
from service.procs import TunerProcess, weights_path

D = BenchConfig()
"""The defaults, which the options' defaults are."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    a = parser.add_argument
    a("--loops", type=int, default=D.loops, help="simulated loops (default 10000)")
    a("--rate", type=float, default=D.rate, help="samples per second per loop (default 1)")
    a("--duration", type=float, default=D.duration, help="measured window, seconds (default 60)")
    a("--warmup", type=float, default=D.warmup, help="seconds before the window (default 10)")
    a("--aligned", action="store_true", help="worst case: all loops sampled and due together")
    a("--per-loop", action="store_true",
      help="one message per sample and per gains update instead of batches")  # fmt: skip
    a("--per-loop-gains", action="store_true",
      help="batched samples, but one gains message per loop and update")  # fmt: skip
    a("--batch-size", type=int, default=D.batch_size, help="most samples per batch message")
    a("--sample-form", choices=["columns", "rows"], default=D.sample_form,
      help="--instances: the gateways' batches as SampleColumns or SampleBatch")  # fmt: skip
    a("--instances", type=int, default=D.instances,
      help="tuners sharing a PostgreSQL store (default 1: one tuner on SQLite)")  # fmt: skip
    a("--gateways", type=int, default=D.gateways,
      help="gateways the loops are spread over (--instances: 4 per instance at least)")  # fmt: skip
    a("--generators", type=int, default=D.generators,
      help="--instances: load generator processes (default: one per instance)")  # fmt: skip
    a("--postgres", default=None, metavar="URL",
      help="the store of --instances (default: a temporary PostgreSQL server)")  # fmt: skip
    a("--tick", type=float, default=D.tick, help="spacing of the phase groups, seconds")
    a("--tau", type=float, nargs=2, default=D.tau, metavar=("MIN", "MAX"),
      help="range of plant time constants, seconds (RL period = 5.5 tau)")  # fmt: skip
    a("--agent-weights", type=weights_path, default=None,
      help="weights file for the daemon (default: shipped)")  # fmt: skip
    a(
        "--inference-threads",
        type=int,
        default=D.inference_threads,
        help="torch threads of the daemon",
    )
    a(
        "--inference-workers",
        type=int,
        default=D.inference_workers,
        help="threads stepping one large batch",
    )
    a(
        "--inference-precision",
        choices=["auto", "float32", "bfloat16"],
        default=D.inference_precision,
        help="GEMM arithmetic of the daemon and of the inference timing",
    )
    a(
        "--snapshot-interval",
        type=float,
        default=D.snapshot_interval,
        help="daemon snapshot period, s",
    )
    a("--memory-probe", type=int, default=D.memory_probe,
      help="register this many loops first to measure RSS per loop (0: skip)")  # fmt: skip
    a("--monitor-ab", type=int, default=D.monitor_ab, metavar="PAIRS",
      help="measure the monitoring's CPU cost: PAIRS interleaved runs with it on and off "
           "(daemon CPU seconds per accepted sample)")  # fmt: skip
    a("--pin", default=None, metavar="DAEMON:GEN",
      help="pin daemon and generator to CPU lists, e.g. 0:1")  # fmt: skip
    a("--seed", type=int, default=D.seed)
    a("--out", type=Path, default=D.out, help="results directory")
    a("--no-inference-bench", action="store_true", help="skip the in-process inference timing")
    a("--daemon-log", type=Path, default=None,
      help="keep the daemon's log here (--instances: a directory, one log per member)")  # fmt: skip
    a("--trace", type=Path, default=None,
      help="write the update latencies of the window to this CSV")  # fmt: skip
    a("--guard", type=guard_option, default=None, metavar="JSON",
      help="guard settings added to every loop's registration, e.g. "
      "'{\"identify\": true, \"auto_rescale\": true}' (default: the gate off only)")  # fmt: skip
    a("--no-hint", action="store_true",
      help="register the loops without a scaling hint: identified before they are tuned "
      "(the update latencies then count the identified loops' agent steps)")  # fmt: skip
    retention.add_arguments(parser)


def bench_config(args: argparse.Namespace) -> BenchConfig:
    """The parsed options as a :class:`BenchConfig`."""
    values = {f.name: getattr(args, f.name) for f in fields(BenchConfig)}
    return BenchConfig(**{**values, "tau": tuple(values["tau"])})


def start_daemon(
    config: BenchConfig, workdir: Path, env: dict[str, str] | None = None
) -> TunerProcess:
    """The tuner under test, on a fresh database, without an API token, with ``env``
    added to its environment; ready."""
    log = config.daemon_log or workdir / "daemon.log"
    log.unlink(missing_ok=True)  # this run's log only
    extra = ("--agent-weights", config.agent_weights) if config.agent_weights else ()
    daemon = TunerProcess(
        workdir / "bench.db", "--instance-id", "bench", "--log-level", "warning",
        "--snapshot-interval", str(config.snapshot_interval),
        "--inference-threads", str(config.inference_threads),
        "--inference-workers", str(config.inference_workers),
        "--inference-precision", config.inference_precision, *extra,
        log=log, cpus=config.cpus(0), env=env,
    )  # fmt: skip
    daemon.start(timeout=60.0)
    return daemon


def run(args: argparse.Namespace) -> int:
    if args.retention:
        return retention.main(args)
    config = bench_config(args)
    if (
        config.loops < 1 or config.rate <= 0 or config.duration <= 0 or config.warmup < 0
        or config.instances < 1 or config.gateways < 1
    ):  # fmt: skip
        print("pitune bench: --loops, --rate, --duration, --instances, --gateways must be "
              "positive", file=sys.stderr)  # fmt: skip
        return 2
    if config.monitor_ab:
        return monitor_ab.main(config, config.monitor_ab, start_daemon)
    machine = machine_info()
    inference = None
    if not config.no_inference_bench:
        from service.bench.inference import inference_bench  # torch only when timing it

        inference = inference_bench(config, config.loops)
    if config.instances > 1:
        config = scaleout.spread(config)
    with tempfile.TemporaryDirectory(prefix="pitune-bench-") as tmp:
        if config.instances > 1:
            result = scaleout.run(config, Path(tmp))
        else:
            daemon = start_daemon(config, Path(tmp))
            try:
                with httpx.Client(timeout=30) as client:
                    result = drive(config, Fleet(config), daemon, client)
            finally:
                code = daemon.stop()
            result["daemon_exit"] = code
    result.update(config=config.as_json(), machine=machine, inference=inference)
    result["bar"] = judge(result)
    path = write(config, result)
    print(table(result))
    print(f"\nwritten to {path}")
    lost_or_rejected = result["samples"]["lost"] or result["samples"]["rejected"]
    return 1 if lost_or_rejected else 0
