"""Prometheus metrics of one tuner, and rate-limited logging of rejected input.

Each tuner owns its registry, so several tuners in one process (tests) never share
counters. The registry also carries the process's metrics (``process_*``: CPU seconds,
resident memory, open and maximum file descriptors, start time; ``python_gc_*``;
``python_info``), and no counter has a ``_created`` series (``disable_created_metrics``:
they double the exposition and no dashboard reads them).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import orjson
from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    GCCollector,
    Histogram,
    PlatformCollector,
    ProcessCollector,
    disable_created_metrics,
    generate_latest,
)
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

from service.daemon.logs import EventLog
from service.wire.clip import clipped
from service.wire.protocol import LoopStatus, Mode, RejectReason

if TYPE_CHECKING:
    from service.daemon.cluster import Cluster

log = logging.getLogger("pitune.tuner")
disable_created_metrics()  # process-wide: no `_created` series beside any counter


GAUGES = ("_bytes", "_waiting", "_members", "_owned")
"""Name endings of :meth:`Metrics.totals` numbers that are levels (gauges), not counts."""


class _Totals:
    """A collector of numbers kept by the tuner itself (no double bookkeeping)."""

    def __init__(self, read: dict[str, tuple[str, Callable[[], float]]]) -> None:
        self.read = read

    def collect(self):
        for name, (text, value) in self.read.items():
            family = GaugeMetricFamily if name.endswith(GAUGES) else CounterMetricFamily
            yield family(name, text, value=float(value()))


def cluster_totals(cluster: Cluster) -> dict[str, tuple[str, Callable[[], float]]]:
    """A cluster member's numbers (:meth:`Metrics.totals`), as its tick left them."""
    return {
        "pitune_cluster_members": (
            "Live members of the cluster, this one included, at the last tick (fewer than "
            "deployed: one is missing).",
            lambda: len(cluster.members),
        ),
        "pitune_cluster_shards_owned": (
            "Shards whose leases this member holds.",
            lambda: len(cluster.held),
        ),
        "pitune_cluster_takeovers": (
            "Shards this member's ticks acquired after its first tick: from a member that "
            "died or left, or released to it in a rebalance.",
            lambda: cluster.takeovers,
        ),
    }


class Metrics:
    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        r = self.registry
        ProcessCollector(registry=r)
        PlatformCollector(registry=r)
        GCCollector(registry=r)
        self.samples_received = Counter(
            "pitune_samples_received",
            "Samples received on the bus (each sample of a batch counts).",
            registry=r,
        )
        self.samples_rejected = Counter(
            "pitune_samples_rejected", "Samples rejected, by reason.", ["reason"], registry=r
        )
        self.updates_published = Counter(
            "pitune_updates_published", "Gains messages published, by mode.", ["mode"], registry=r
        )
        self.inference_seconds = Histogram(
            "pitune_inference_batch_seconds",
            "Wall time of one batched agent step.",
            buckets=(0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 1.0),
            registry=r,
        )
        self.inference_batch_size = Histogram(
            "pitune_inference_batch_loops",
            "Loops stepped per batched agent call.",
            buckets=(1, 2, 5, 10, 50, 100, 500, 1000, 5000, 10000),
            registry=r,
        )
        self.loops = Gauge("pitune_loops", "Registered loops, by mode.", ["mode"], registry=r)
        self.loops_by_status = Gauge(
            "pitune_loops_by_status",
            "Registered loops by status (tuning, quiet, stale, manual, ...), at scrape time.",
            ["status"],
            registry=r,
        )
        self.queue_depth = Gauge("pitune_queue_depth", "Bus messages waiting.", registry=r)
        self.bus_connected = Gauge(
            "pitune_bus_connected",
            "1 while samples can arrive and gains leave (a router or peer connected, or the "
            "tuner only listens), 0 while cut off.",
            registry=r,
        )
        self.store_commit_failures = Counter(
            "pitune_store_commit_failures",
            "Failed commits of gains and audit rows (nothing was published for them).",
            registry=r,
        )
        self.steps_skipped = Counter(
            "pitune_steps_skipped",
            "Due RL steps skipped because the store failed to commit.",
            registry=r,
        )
        self.hold = Gauge(
            "pitune_hold",
            "1 while the plant-wide hold is in force (the tuner changes no loop's gains of "
            "its own: GET /hold says who set it, when and why), 0 otherwise.",
            registry=r,
        )
        self.loops_unloadable = Gauge(
            "pitune_loops_unloadable",
            "Stored loops not loaded at start-up: their config is invalid (see the log).",
            registry=r,
        )
        # Every label value exists from the start, so dashboards and tests see zeros.
        for reason in RejectReason:
            self.samples_rejected.labels(reason.value)
        for mode in Mode:
            self.loops.labels(mode.value).set(0)
        for mode in (Mode.auto, Mode.advisory):  # frozen loops publish nothing
            self.updates_published.labels(mode.value)
        self._rejections = RateLimitedLog(log)
        self.identification = Counter(
            "pitune_identification",
            "Identification outcomes: identified, rescaled, mismatch, out_of_envelope, "
            "in_envelope, identify, model (a first tuning from a model), refuted.",
            ["outcome"],
            registry=r,
        )
        self.verdicts = Counter(
            "pitune_verdicts",
            "Verdicts of gain changes (verified, rolled_back, rollback_proposed, worse), "
            "by what judged them (iae, overshoot, oscillation, operator; '' for verified).",
            ["verdict", "why"],
            registry=r,
        )
        self.monitor = Gauge(
            "pitune_loops_monitor",
            "Loops by monitoring state at scrape time: oscillating, output_held (the data "
            "show the output at a limit), pv_stalled (no op: the PV does not follow the "
            "output the PI law gives), change_pending "
            "(gains differ from the last-good), held (after a rollback or rejection), "
            "proposal_pending (advisory). Aggregated: no per-loop series.",
            ["state"],
            registry=r,
        )
        self.monitor_means = Gauge(
            "pitune_loops_monitor_mean",
            "Mean over loops of a window figure at scrape time: manual_share, "
            "saturated_share, rejected_share, and of the last response's iae_ratio (its "
            "IAE over the last-good IAE, loops with both).",
            ["figure"],
            registry=r,
        )
        self.events = EventLog()
        """INFO lines of loop changes: ``events.audit(rows)`` with the audit rows committed,
        ``events.published(messages)`` with the gains messages published (see
        :mod:`service.daemon.logs`)."""

    def flush_logs(self) -> None:
        """Sum up rejection bursts and suppressed event lines whose interval is over."""
        self._rejections.flush()
        self.events.flush()

    def reject(self, reason: RejectReason, loop_id: str | None, detail: str, n: int = 1) -> None:
        """Count ``n`` rejected samples and log it (at most once per interval and reason).

        ``loop_id`` and ``detail`` may come straight from the wire (a loop id, a samples
        key): logged clipped and with repr, so that none forges log lines (a newline) or
        terminal escapes, or makes one megabytes long."""
        self.samples_rejected.labels(reason.value).inc(n)
        shown = None if loop_id is None else clipped(loop_id)
        self._rejections.warning(
            reason.value, f"sample rejected ({reason}) loop={shown!r}: {clipped(detail)!r}"
        )

    def set_status_counts(self, counts: dict[LoopStatus, int]) -> None:
        for status in LoopStatus:
            self.loops_by_status.labels(status.value).set(counts.get(status, 0))

    def set_monitor(self, counts: dict[str, int], means: dict[str, float]) -> None:
        for state, n in counts.items():
            self.monitor.labels(state).set(n)
        for figure, value in means.items():
            self.monitor_means.labels(figure).set(value)

    def verdict(self, rows) -> None:
        """Count the verdicts among committed audit rows."""
        for row in rows:
            reason = row[5]
            if reason == "verified":
                self.verdicts.labels("verified", "").inc()
            elif reason in ("rollback", "verdict"):
                detail = orjson.loads(row[10])
                self.verdicts.labels(detail["verdict"], detail.get("why", "")).inc()

    def set_loop_counts(self, counts: dict[Mode, int]) -> None:
        for mode in Mode:
            self.loops.labels(mode.value).set(counts.get(mode, 0))

    def totals(self, read: dict[str, tuple[str, Callable[[], float]]]) -> None:
        """Counters kept as plain numbers elsewhere (name: (help, reader)), read at each
        scrape; a name ending in one of :data:`GAUGES` is a gauge."""
        self.registry.register(_Totals(read))

    def render(self) -> bytes:
        return generate_latest(self.registry)

    def value(self, name: str, **labels: str) -> float:
        """Current value of a sample (tests and the admin API)."""
        v = self.registry.get_sample_value(name, labels or None)
        return 0.0 if v is None else v


class RateLimitedLog:
    """Log at most one message per key and interval, reporting how many were suppressed."""

    def __init__(self, logger: logging.Logger, interval_s: float = 5.0) -> None:
        self.logger = logger
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warning(self, key: str, message: str) -> bool:
        now = time.monotonic()
        if now - self._last.get(key, -float("inf")) < self.interval_s:
            self._suppressed[key] = self._suppressed.get(key, 0) + 1
            return False
        suppressed = self._suppressed.pop(key, 0)
        if suppressed:
            message += f" ({suppressed} similar suppressed)"
        self._last[key] = now
        self.logger.warning(message)
        return True

    def flush(self) -> None:
        """Log the count of messages suppressed in intervals that are over: the end of
        a burst is reported even if no message of its key follows."""
        now = time.monotonic()
        for key, count in list(self._suppressed.items()):
            if now - self._last.get(key, -float("inf")) >= self.interval_s:
                del self._suppressed[key]
                self.logger.warning(
                    "%d more %s messages suppressed in the last %.0f s",
                    count,
                    key,
                    now - self._last[key],
                )
