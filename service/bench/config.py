"""What one ``pitune bench`` run does: the load, the daemon's settings, the outputs."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

from service.procs import ROOT

RESULTS = ROOT / "benchmarks" / "results"
GATEWAY = "bench"
"""The gateway the loops are registered with (batched gains), unless per-loop gains."""


@dataclass(frozen=True)
class BenchConfig:
    """The benchmark's settings; the field names are the options' (``--per-loop`` is
    ``per_loop``) and the keys of the results' ``config``."""

    loops: int = 10_000
    rate: float = 1.0
    """Samples per second per loop."""
    duration: float = 60.0
    """The measured window, seconds."""
    warmup: float = 10.0
    """Seconds before the window."""
    aligned: bool = False
    """Worst case: all loops sampled at the same instant and due together."""
    per_loop: bool = False
    """One message per sample and per gains update instead of batches."""
    per_loop_gains: bool = False
    """Batched samples, but one gains message per loop and update."""
    gateways: int = 1
    """Gateways the loops are spread over (a cluster's members own whole gateways)."""
    instances: int = 1
    """Tuner processes sharing a PostgreSQL store (1: one tuner on SQLite)."""
    generators: int = 0
    """Load generator processes of ``instances`` > 1 (0: one per instance)."""
    postgres: str | None = None
    """The PostgreSQL URL for ``instances`` > 1 (None: a temporary server)."""
    batch_size: int = 2000
    """Most samples per batch message."""
    sample_form: str = "columns"
    """``--instances``: the gateways' batches as ``columns`` (SampleColumns, revision 6)
    or ``rows`` (SampleBatch)."""
    tick: float = 0.01
    """Spacing of the phase groups of the sample clock, seconds."""
    tau: tuple[float, float] = (5.0, 30.0)
    """Range of plant time constants, seconds (RL period = 5.5 tau)."""
    agent_weights: str | None = None
    """Weights file of the daemon (None: shipped; ``untrained``: random)."""
    inference_threads: int = 1
    inference_workers: int = 1
    inference_precision: str = "auto"
    snapshot_interval: float = 30.0
    memory_probe: int = 1000
    """Register this many loops first to measure the RSS per loop (0: skip)."""
    monitor_ab: int = 0
    """On/off pairs of the monitoring's cost (:mod:`service.bench.monitor_ab`; 0: an
    ordinary run)."""
    pin: str | None = None
    """``DAEMON:GEN`` CPU lists, e.g. ``0:1``."""
    seed: int = 0
    out: Path = RESULTS
    no_inference_bench: bool = False
    daemon_log: Path | None = None
    trace: Path | None = None
    """Write the update latencies of the window to this CSV."""
    guard: dict | None = None
    """Guard settings added to every loop's registration (e.g. identification on: what
    an opt-in measure costs at this load); None: the benchmark's own (the gate off)."""
    no_hint: bool = False
    """Register the loops without a scaling hint: each is identified from its own data
    before it is tuned (a site commissioned without models)."""

    @property
    def batched_gains(self) -> bool:
        """Gains come in the bench gateway's batches (else one message per loop)."""
        return not (self.per_loop or self.per_loop_gains)

    def cpus(self, who: int) -> set[int] | None:
        """The CPUs ``--pin`` gives the daemon (0) or the generator (1), if any."""
        if self.pin is None:
            return None
        return {int(c) for c in self.pin.split(":")[who].split(",") if c}

    def as_json(self) -> dict:
        """The settings as JSON values (paths as strings), for the results."""
        return json.loads(json.dumps(asdict(self), default=str))
