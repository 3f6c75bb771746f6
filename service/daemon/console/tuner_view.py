"""The tuner page's figures: counters, inference latency, store and process health,
and rates from the counters' growth between polls."""

from __future__ import annotations

import collections
import math
import threading

from service.wire.protocol import Mode, RejectReason

_INFERENCE_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.25, 1.0)


def _quantile(m, name: str, q: float) -> float | None:
    """Upper bound of the histogram bucket holding the quantile ``q``."""
    total = m.value(f"{name}_count")
    if not total:
        return None
    for le in _INFERENCE_BUCKETS:
        if m.value(f"{name}_bucket", le=str(le)) >= q * total:
            return le
    return math.inf


def tuner_figures(tuner) -> dict:
    m = tuner.metrics
    rejected = {r.value: int(m.value("pitune_samples_rejected_total", reason=r.value))
                for r in RejectReason}  # fmt: skip
    updates = {mode.value: int(m.value("pitune_updates_published_total", mode=mode.value))
               for mode in Mode}  # fmt: skip
    inf = "pitune_inference_batch_seconds"
    count = m.value(f"{inf}_count")
    store = tuner.store
    recent = getattr(tuner, "recent", None)  # no ring in tuners built without one
    return {
        "alive": tuner.alive,
        "ready": tuner.ready,
        "bus_ready": tuner.bus_ready,
        "instance_id": tuner.settings.instance_id,
        "epoch": tuner.epoch,
        "key_prefix": tuner.settings.key_prefix,
        "inference_precision": str(tuner.table.inference_precision),
        "queue_depth": tuner.inbox.qsize(),
        "queue_size": tuner.settings.queue_size,
        "received": int(m.value("pitune_samples_received_total")),
        "rejected": rejected,
        "rejected_total": sum(rejected.values()),
        "updates": updates,
        "inference": {
            "batches": int(count),
            "mean_ms": m.value(f"{inf}_sum") / count * 1000 if count else None,
            "p50_le_ms": _ms(_quantile(m, inf, 0.5)),
            "p99_le_ms": _ms(_quantile(m, inf, 0.99)),
            "loops_per_batch": (
                m.value("pitune_inference_batch_loops_sum") / count if count else None
            ),
        },
        "store": {
            "ok": tuner.store_failure is None,
            "failure": tuner.store_failure,
            # (a PostgreSQL URL's password redacted)
            "path": store.location if store is not None else None,
            "journal_rows": store.journal_rows if store is not None else None,
            "commit_failures": int(m.value("pitune_store_commit_failures_total")),
            "steps_skipped": int(m.value("pitune_steps_skipped_total")),
        },
        "queries_dropped": tuner.queries_dropped,
        "superseded": tuner.superseded,
        "process": {
            "rss_mb": m.value("process_resident_memory_bytes") / 2**20,
            "cpu_s": m.value("process_cpu_seconds_total"),
            "open_fds": int(m.value("process_open_fds")),
        },
        "trends_mb": recent.nbytes / 2**20 if recent is not None else None,
    }


def _ms(x: float | None) -> float | str | None:
    if x is None:
        return None
    return "> 1000" if math.isinf(x) else x * 1000


class Rates:
    """Rates from the counters' growth over the last ~10 s of polls."""

    def __init__(self) -> None:
        self.points: collections.deque = collections.deque()
        self.lock = threading.Lock()

    def rates(self, now: float, values: dict[str, float]) -> dict[str, float | None]:
        with self.lock:
            self.points.append((now, values))
            while len(self.points) > 2 and now - self.points[1][0] >= 10.0:
                self.points.popleft()
            then, old = self.points[0]
        dt = now - then
        if dt < 0.5:
            return {k: None for k in values}
        return {k: (v - old[k]) / dt for k, v in values.items()}
