"""The tuner daemon's core: the tuning engine wired to the store and the bus, with one
worker thread.

:class:`Tuner` is the daemon minus its HTTP server: ``start()`` restores the loops from
the store into the engine and opens the bus, ``stop()`` closes the bus, drains what was
received, snapshots and closes the store. The admin API calls its methods; tests can
run it in-process.

The worker drains the bus queue in batches: sample messages are decoded
(:mod:`service.wire.decode`) and handed to the engine (:mod:`service.engine`), which
says which loops fall due; due loops are stepped in one batched agent call at the end
of the batch (earlier if a due loop receives another sample). Gains and audit rows are
committed to the store (as one journal row per step batch, see
:mod:`service.daemon.store`) before the gains messages go out: one message per loop, or
one per gateway for loops registered with a gateway. The worker applies the journal to
the store's tables while it has nothing else to do. Nothing about tuning is decided
here: this module owns lifecycle, persistence policy and publishing.

Accounting: every sample received ends in exactly one counter, accepted (the loops'
``samples``) or rejected (by reason), and ``pitune_samples_received_total`` is counted
*after* the samples are judged, so once it reaches N those N are in their counters. A
message dropped unread (the inbox full: ``overload``; over
:data:`~service.wire.protocol.MAX_MESSAGE_BYTES`: ``too_large``) counts as one received
and one rejected sample whatever it held: not reading it is the point of dropping it.

Publishing never holds the worker: committed gains go to a :class:`Lane` per
destination (one for the per-loop keys, one per gateway), each with its own thread
doing the blocking put, in order; past LANE_BOUND waiting messages a lane keeps only
the newest of each loop (gains are absolute and gateways drop older seqs), so it stays
bounded, and a stuck gateway delays only its own lane.

Retention: in idle time the worker prunes the audit history by the settings'
``history_*`` policy (:meth:`Store.prune`), PRUNE_CHUNK loops per iteration.
"""

from __future__ import annotations

import collections
import contextlib
import gc
import logging
import math
import os
import queue
import sqlite3
import threading
import time
from collections.abc import Callable

import orjson
import torch
import zenoh

from service.agent.model import Agent, load_agent, untrained_agent
from service.daemon.bus import JSON, Bus, Inbox, Item, Kind, reply
from service.daemon.metrics import Metrics, RateLimitedLog
from service.daemon.recent import Recent
from service.daemon.schemas import HistoryPage, LoopsPage
from service.daemon.settings import Settings
from service.daemon.store import Store
from service.daemon.verdicts import SCAN, annotate
from service.engine import views
from service.engine.audit import AuditRow, audit_row
from service.engine.config import LoopConfig, LoopPatch, LoopView
from service.engine.engine import TuningEngine
from service.engine.figures import Performance
from service.engine.updates import StepResult
from service.wire.decode import Rejection, decode_batch, decode_singles
from service.wire.protocol import (
    MAX_BATCH,
    SCHEMA_VERSION,
    ErrorReply,
    RejectReason,
    StateBatch,
    StateReply,
    encode,
)

log = logging.getLogger("pitune.tuner")
_STOP = (None, "", None)
SNAPSHOT_CHUNK = 1000
"""Loops snapshotted per worker iteration by the periodic snapshot."""
FLUSH_AFTER_S = 0.002
"""Longest a due loop waits for more due loops to join its batch while a backlog drains."""
JOURNAL_CHUNK = 1000
"""Journal rows applied to the store's tables per idle worker iteration (~5 ms)."""
JOURNAL_BACKLOG = 100_000
"""Journal rows pending above which they are applied even while messages wait."""
COMMIT_RETRY_S = 1.0
"""Seconds between attempts to commit while the store fails."""
EXIT_STORE_FAILED = 74
"""Exit status after ``store_failure_exit_s`` of failing commits (EX_IOERR)."""
_RANGE_ERRORS = {"less_than_equal", "greater_than_equal", "less_than", "greater_than"}
AFTER_T_WAIT_S = 1.0
"""Longest a state query with ``after_t`` waits for its loop's sample."""
PRUNE_CHUNK = 200
"""Loop ids whose audit history is pruned per idle worker iteration."""
LANE_BOUND = 100_000
"""Messages a lane holds before it keeps only the newest of each loop."""
LANE_DRAIN_S = 5.0
"""Longest :meth:`Tuner.stop` waits for the lanes to publish what they hold."""


class Lane:
    """Committed gains messages waiting for one destination, and the thread publishing
    them: the per-loop keys (``gateway`` None) or one gateway's GainsBatch key.

    Messages go out in the order submitted. While the destination blocks, messages
    pile up; past ``bound`` of them, only the newest of each loop is kept (gains are
    absolute, and gateways drop a seq below one they took), so a lane holds at most
    ``max(bound, loops)`` messages however long its destination blocks.
    """

    def __init__(
        self,
        gateway: str | None,
        send: Callable[[str | None, list[dict]], None],
        bound: int = LANE_BOUND,
    ):
        self.gateway = gateway
        self._send = send
        self.bound = bound
        self._pending: list[dict] = []
        self._cond = threading.Condition()
        self._busy = False
        self._closing = False
        self.superseded = 0
        """Messages replaced by a newer one of the same loop before they went out."""
        self.thread = threading.Thread(
            target=self._run, name=f"pitune-publish-{gateway or 'loops'}", daemon=True
        )
        self.thread.start()

    def submit(self, messages: list[dict]) -> None:
        with self._cond:
            self._pending.extend(messages)
            if len(self._pending) > self.bound:
                newest = {m["loop_id"]: i for i, m in enumerate(self._pending)}
                kept = [self._pending[i] for i in sorted(newest.values())]
                self.superseded += len(self._pending) - len(kept)
                self._pending = kept
            self._cond.notify_all()

    def _run(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._closing:
                    self._cond.wait()
                if not self._pending:
                    return
                batch, self._pending = self._pending, []
                self._busy = True
            try:
                self._send(self.gateway, batch)
            except Exception:
                log.exception("publishing %d gains messages failed", len(batch))
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    @property
    def idle(self) -> bool:
        return not self._pending and not self._busy

    def drain(self, timeout: float) -> bool:
        """Wait until everything submitted went out; False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self._pending or self._busy:
                left = deadline - time.monotonic()
                if left <= 0.0:
                    return False
                self._cond.wait(left)
            return True

    def close(self, timeout: float) -> None:
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self.thread.join(timeout)


IDENTIFICATION_OUTCOMES = frozenset(
    {"identified", "rescaled", "mismatch", "out_of_envelope", "in_envelope", "identify"}
)
"""Audit reasons of the engine's identification (counted per outcome)."""


class Conflict(Exception):
    """The loop already exists."""


class UnknownLoop(LookupError):
    """No loop with this id."""


class StoreUnavailable(Exception):
    """The store fails to commit: the change would be neither recorded nor published."""


def load_configured_agent(settings: Settings) -> Agent:
    """The agent the settings ask for; the untrained one only with a loud warning."""
    if settings.agent_weights == "untrained":
        log.warning("using an UNTRAINED agent (agent_weights=untrained): updates are noise")
        return untrained_agent(0)
    if settings.agent_weights:
        return load_agent(settings.agent_weights)
    try:
        return load_agent()
    except FileNotFoundError:
        log.warning(
            "\n%s\nNO TRAINED AGENT WEIGHTS FOUND (service/models/pitune_agent.pt): falling back "
            "to an UNTRAINED agent whose gain updates are noise. Pass --agent-weights.\n%s",
            "!" * 78,
            "!" * 78,
        )
        return untrained_agent(0)


def _freeze_survivors() -> None:
    """Move the objects that survived so far out of the cyclic GC's reach.

    Under a stream of 10,000 samples/s the GC runs full collections every few seconds;
    each scans every long-lived tracked object (modules, caches the HTTP stack builds on
    its first requests, ...): ~100 ms per collection, a stall of the sample stream. The
    tuner freezes what exists at start-up, after a bulk registration and after every
    periodic snapshot, so the full collections the sample stream triggers only see
    recent objects. Frozen objects are still freed by reference counting, and a full
    collection runs first (cheap: it scans only what is not frozen yet), so no cyclic
    garbage is frozen.
    """
    gc.collect()
    gc.freeze()


SINGLES_GROUP = 2000
"""Most single-sample messages ingested in one vectorised pass."""


def _group_singles(items: list[Item]):
    """The items, with runs of single-sample messages as (Kind.sample, "", [(key, payload)])."""
    run: list[tuple[str, bytes]] = []
    for kind, key, payload in items:
        if kind is Kind.sample:
            run.append((key, payload))
            if len(run) < SINGLES_GROUP:
                continue
        if run:
            yield Kind.sample, "", run
            run = []
        if kind is not Kind.sample:
            yield kind, key, payload
    if run:
        yield Kind.sample, "", run


class Tuner:
    def __init__(self, settings: Settings, agent: Agent | None = None) -> None:
        self.settings = settings
        self.keys = settings.keys
        self.metrics = Metrics()
        self.agent = agent if agent is not None else load_configured_agent(settings)
        self.engine = TuningEngine(
            self.agent,
            max_rate_hz=settings.max_sample_rate_hz,
            inference_workers=settings.inference_workers,
            inference_precision=settings.inference_precision,
            on_reject=self._on_reject,
        )
        self.table = self.engine.table
        self.recent = Recent(known=self.table.slot_of)
        """Recent samples and published gains of each loop, for the console's trends."""
        self._skipped = 0
        self.inbox = Inbox(settings.queue_size, settings.queue_bytes)
        self.epoch: int | None = None
        """The store's epoch of this run (set by :meth:`start`)."""
        self.lanes: dict[str | None, Lane] = {}
        self._lanes_lock = threading.Lock()
        self._parked: dict[str, list[tuple[float, float, zenoh.Query]]] = {}
        """State queries with ``after_t`` waiting for their loop's sample: loop id ->
        [(after_t, monotonic deadline, query)]."""
        self.queries_dropped = 0
        """State queries dropped unanswered because the inbox was full."""
        self._prune_todo: list[str] = []
        self._next_prune = 0.0
        self.pruned = 0
        """Audit rows deleted by the retention policy since start."""
        self.metrics.totals(
            {
                "pitune_state_queries_dropped": (
                    "State queries dropped unanswered (input queue full).",
                    lambda: self.queries_dropped,
                ),
                "pitune_gains_superseded": (
                    "Gains messages replaced in a blocked lane by a newer one of their loop.",
                    lambda: self.superseded,
                ),
                "pitune_audit_pruned": (
                    "Audit rows deleted by the retention policy.",
                    lambda: self.pruned,
                ),
                "pitune_queue_bytes": (
                    "Payload bytes waiting in the input queue.",
                    lambda: self.inbox.nbytes,
                ),
            }
        )
        self.store: Store | None = None
        self.bus: Bus | None = None
        self._worker: threading.Thread | None = None
        self._snapshot_todo: list[str] = []
        self._held: list[StepResult] = []
        """Steps whose commit failed: published once a commit succeeds."""
        self._store_failing_since: float | None = None
        self._store_error = ""
        self._retry_at = 0.0
        self._failure_log = RateLimitedLog(log)

    # -- lifecycle --------------------------------------------------------------------
    def start(self) -> Tuner:
        self.store = Store(self.settings.db_path)
        wall = time.time()
        self.epoch = self.store.next_epoch(wall)
        with self.table.lock:
            for stored in self.store.load():
                self.engine.restore(
                    stored.config,
                    kp=stored.kp,
                    ki=stored.ki,
                    seq=stored.seq,
                    hidden=stored.hidden,
                    runtime=stored.runtime,
                    wall=wall,
                )
            self.metrics.set_loop_counts(self.table.mode_counts())
        self.metrics.loops_unloadable.set(len(self.store.unloadable))
        log.info("restored %d loops from %s", len(self.table), self.settings.db_path)
        # Everything allocated so far (modules, torch, the restored table) lives as long as
        # the process: keep it out of the cyclic GC's full collections (~100 ms each).
        _freeze_survivors()
        self.bus = Bus(self.settings, self.inbox, self._overload)
        try:
            self.bus.open()
        except BaseException:
            self.store.close()
            raise
        self._worker = threading.Thread(target=self._run, name="pitune-worker", daemon=True)
        self._worker.start()
        log.info(
            "tuner %s (epoch %d) up: prefix %r, listen %s, connect %s, inference %s",
            self.settings.instance_id,
            self.epoch,
            self.settings.key_prefix,
            self.settings.zenoh_listen,
            self.settings.zenoh_connect,
            self.table.inference_precision,
        )
        return self

    def stop(self) -> None:
        """Stop receiving, handle what was already received, publish what is committed
        (at most LANE_DRAIN_S), close the bus, snapshot, close the store."""
        if self.bus is not None:
            self.bus.stop_receiving()
        if self._worker is not None:
            self.inbox.put(_STOP)
            self._worker.join(timeout=30.0)
            self._worker = None
        deadline = time.monotonic() + LANE_DRAIN_S
        for lane in list(self.lanes.values()):
            if not lane.drain(max(0.0, deadline - time.monotonic())):
                log.warning("gains for %s not all published at stop", lane.gateway or "loops")
        if self.bus is not None:
            self.bus.close()
        for lane in list(self.lanes.values()):
            lane.close(timeout=1.0)
        if self.store is not None:
            self.snapshot()
            self.store.close()
            self.store = None
        log.info("tuner %s stopped", self.settings.instance_id)

    def __enter__(self) -> Tuner:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def alive(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    @property
    def bus_ready(self) -> bool:
        """Samples can arrive and gains can leave: the session is open and, if this tuner
        connects to routers or peers, one is connected (see :attr:`Bus.connected`)."""
        return self.bus is not None and self.bus.connected

    @property
    def ready(self) -> bool:
        """The worker runs and the bus is ready (``/readyz``)."""
        return self.alive and self.bus_ready

    def snapshot(self) -> None:
        """Snapshot every loop now (shutdown, tests)."""
        self._write_snapshot(None)
        self._snapshot_todo = []

    def _snapshot_some(self) -> None:
        """The periodic snapshot, SNAPSHOT_CHUNK loops per worker iteration, so that
        snapshotting a large site never stalls the samples for long."""
        chunk, self._snapshot_todo = (
            self._snapshot_todo[:SNAPSHOT_CHUNK],
            self._snapshot_todo[SNAPSHOT_CHUNK:],
        )
        self._write_snapshot(chunk)
        if not self._snapshot_todo:
            _freeze_survivors()

    def _write_snapshot(self, loop_ids: list[str] | None) -> None:
        # Written under the table lock (a few ms per chunk): a delete between reading the
        # rows and writing them would fail the whole chunk on the foreign key, and a
        # delete and a new registration of the id would give the new loop the old state.
        with self.table.lock:
            self.store.snapshot(self.table.snapshot(loop_ids))

    # -- worker -----------------------------------------------------------------------
    def _run(self) -> None:
        # Thread counts of OpenMP and MKL (torch's tanh/sigmoid go through MKL VML) are
        # per thread: set them where inference runs, or MKL forks a team of threads per op
        # that, on a busy box, waits for CPU time (a step of 5 loops took ~90 ms).
        torch.set_num_threads(self.settings.inference_threads)
        interval = self.settings.snapshot_interval_s
        next_snapshot = time.monotonic() + interval
        while True:
            try:
                if self._store_failing_since is not None:  # until the next retry
                    wait = self._retry_at - time.monotonic()
                elif self._snapshot_todo or self.store.journal_rows or self._prune_todo:
                    wait = 0.0
                else:
                    wait = min(next_snapshot, self._next_prune) - time.monotonic()
                if self._parked:  # the earliest after_t query to answer anyway
                    first = min(d for q in self._parked.values() for _, d, _ in q)
                    wait = min(wait, first - time.monotonic())
                items = [self.inbox.get(timeout=max(0.0, wait))]
            except queue.Empty:
                items = []
            while items and len(items) < self.settings.max_batch:
                try:
                    items.append(self.inbox.get_nowait())
                except queue.Empty:
                    break
            stop = any(item is _STOP for item in items)
            try:
                self._handle([item for item in items if item is not _STOP])
                if self._store_failing_since is not None and not stop:
                    continue  # no journal or snapshot work on a failing store
                self._apply_journal()
                if stop:
                    self.snapshot()
                elif self._snapshot_todo:
                    self._snapshot_some()
                elif time.monotonic() >= next_snapshot:
                    next_snapshot = time.monotonic() + interval
                    with self.table.lock:
                        self._snapshot_todo = list(self.table.slot_of)
                    self._snapshot_some()
                elif self.inbox.empty():
                    self._retain()
            except Exception:
                log.exception("worker iteration failed; continuing")
            if stop:
                return

    def _retain(self) -> None:
        """The retention policy, PRUNE_CHUNK loop ids per idle worker iteration, a pass
        every ``history_prune_interval_s`` (see :meth:`Store.prune`)."""
        st = self.settings
        if not self._prune_todo:
            if time.monotonic() < self._next_prune:
                return
            self._next_prune = time.monotonic() + getattr(st, "history_prune_interval_s", 3600.0)
            self._prune_todo = self.store.audit_ids()
        chunk, self._prune_todo = self._prune_todo[:PRUNE_CHUNK], self._prune_todo[PRUNE_CHUNK:]
        max_age_days = getattr(st, "history_max_age_days", None)
        self.pruned += self.store.prune(
            chunk,
            older_than=None if max_age_days is None else time.time() - max_age_days * 86400.0,
            keep_rows=getattr(st, "history_max_rows_per_loop", None),
            keep_rows_deleted=getattr(st, "history_max_rows_deleted", None),
            archive=getattr(st, "history_archive", None),
        )

    def _apply_journal(self) -> None:
        """A chunk of the journal into the store's tables, when no message waits (or the
        backlog grew large): off the path from a sample to its gains message."""
        if self.inbox.empty() or self.store.journal_rows > JOURNAL_BACKLOG:
            self.store.apply_journal(JOURNAL_CHUNK)

    def _handle(self, items: list[Item]) -> None:
        self.metrics.queue_depth.set(self.inbox.qsize())
        if not items:
            if self._store_failing_since is not None:
                with self.table.lock:
                    self._commit(None)  # retry, even without traffic
            if self._parked:
                with self.table.lock:
                    self._answer_parked()
            return
        wall = time.time()
        engine = self.engine
        flush_at = math.inf
        with engine.lock:
            engine.stepping = self._store_failing_since is None
            for kind, _key, payload in _group_singles(items):
                if kind is Kind.query or kind is Kind.gateway_query:
                    self._flush(wall)  # the reply reflects every sample handled before it
                    if kind is Kind.query:
                        self._answer(payload)
                    else:
                        self._answer_gateway(payload)
                    continue
                if kind is Kind.sample:
                    decoded = decode_singles([(self.keys.loop_id(k), p) for k, p in payload])
                else:
                    decoded = decode_batch(payload)
                self._ingest(decoded, wall)
                # received last: once it reaches N, those N samples are in their counters
                self.metrics.samples_received.inc(decoded.received)
                # Batch the due loops, but never hold one back for long behind a backlog.
                if not engine.due:
                    flush_at = math.inf
                elif flush_at == math.inf:
                    flush_at = time.perf_counter() + FLUSH_AFTER_S
                elif time.perf_counter() >= flush_at:
                    self._flush(wall)
                    flush_at = math.inf
            self._flush(wall)
            self._commit(None)
            if self._parked:
                self._answer_parked()

    def _ingest(self, decoded, wall: float) -> None:
        """Samples into the engine. Should the engine fail (a defect), the samples it had
        not judged yet are counted as rejected ``internal`` and the worker goes on with
        the next message: one bad message never takes the others with it."""
        engine, tb = self.engine, self.table
        self.recent.safely(self.recent.add_samples, decoded.rows)  # the console's trends
        before = sum(engine.rejected.values()) + int(tb.n_samples.sum())
        try:
            for result in engine.ingest_decoded(decoded, wall=wall):
                self._stepped(result)
        except Exception as exc:
            judged = sum(engine.rejected.values()) + int(tb.n_samples.sum()) - before
            lost = max(decoded.received - judged, 0)
            log.exception(
                "handling %d samples failed; %d counted as internal", decoded.received, lost
            )
            if lost:
                self.metrics.samples_rejected.labels(RejectReason.internal.value).inc(lost)
                engine.rejected[RejectReason.internal] += lost
            del exc

    def _on_reject(self, rejection: Rejection) -> None:
        self.metrics.reject(rejection.reason, rejection.loop_id, rejection.detail)

    def _flush(self, wall: float) -> None:
        result = self.engine.flush(wall)
        if self.engine.skipped != self._skipped:
            # A step could be neither committed nor published, and the next one would
            # start from gains the gateway never got: skipped until the store works again.
            self.metrics.steps_skipped.inc(self.engine.skipped - self._skipped)
            self._skipped = self.engine.skipped
        if result is not None:
            self._stepped(result)

    def _stepped(self, result: StepResult) -> None:
        self.metrics.inference_seconds.observe(result.inference_s)
        self.metrics.inference_batch_size.observe(len(result))
        self._commit(result)

    def _commit(self, result: StepResult | None) -> None:
        """Persist the table's pending changes, then publish ``result``'s gains.

        If the store fails (disk full, database locked), the changes go back to the table
        and ``result`` is held, unpublished: nothing goes out that is not committed. A
        later call (the worker retries every COMMIT_RETRY_S) commits them all and then
        publishes what was held, in order.
        """
        if result is not None:
            self._held.append(result)
        if self._store_failing_since is not None and time.monotonic() < self._retry_at:
            return
        gains, audit = self.table.drain_changes()
        for row in audit:
            if row[5] in IDENTIFICATION_OUTCOMES:  # counted, and its state saved promptly
                self.metrics.identification.labels(row[5]).inc()
                self._snapshot_todo.append(row[0])
        dirty = self.table.drain_verify_dirty()
        if gains or audit:
            try:
                self.store.record_gains(gains, audit)
            except Exception as exc:  # sqlite3.Error, OSError, MemoryError: all the same
                self.table.requeue(gains, audit)
                self.table.requeue_verify_dirty(dirty)
                self._store_failed(exc)
                return
            # INFO per gain change / adoption, rate-limited (the API logs resets with their caller)
            self.metrics.events.audit(row for row in audit if row[5] != "reset")
            self.metrics.verdict(audit)
        if dirty:
            # last-good gains, verdicts and proposals on disk before what follows from
            # them goes out: a SIGKILL after this keeps them (they resume on restart)
            try:
                self.store.snapshot(self.table.snapshot(dirty))
            except Exception as exc:  # noqa: BLE001 - as above
                self.table.requeue_verify_dirty(dirty)
                self._store_failed(exc)
                return
        if self._store_failing_since is not None:
            log.warning("store commits work again; publishing %d held steps", len(self._held))
            self._store_failing_since = None
        held, self._held = self._held, []
        for result in held:
            self._publish(result)

    def _store_failed(self, exc: Exception) -> None:
        now = time.monotonic()
        self.metrics.store_commit_failures.inc()
        self._retry_at = now + COMMIT_RETRY_S
        if self._store_failing_since is None:
            self._store_failing_since = now
        failing_for = now - self._store_failing_since
        self._store_error = f"store commits failing for {failing_for:.0f} s: {exc!r}"
        self._failure_log.warning("store", f"{self._store_error}; no RL steps until it works")
        if failing_for >= self.settings.store_failure_exit_s:
            # Unpublished steps live only in memory: restarting from the store brings the
            # tuner back to exactly what was published (as a SIGKILL would), which a store
            # that works again after a restart (or on another volume) needs.
            log.critical("%s: exiting for a supervisor to restart the tuner", self._store_error)
            logging.shutdown()
            os._exit(EXIT_STORE_FAILED)

    @property
    def store_failure(self) -> str | None:
        """Why the store fails to commit, while it does (None: it works)."""
        return None if self._store_failing_since is None else self._store_error

    def _publish(self, result: StepResult) -> None:
        """Hand a committed step's messages to their lanes (never blocks on the bus)."""
        self.recent.safely(self.recent.add_gains, result)
        messages = result.messages(self.settings.instance_id)
        by_gateway: dict[str | None, list[dict]] = collections.defaultdict(list)
        for message, gateway in zip(messages, result.gateways, strict=True):
            message["epoch"] = self.epoch
            by_gateway[gateway].append(message)
        for gateway, batch in by_gateway.items():
            self._lane(gateway).submit(batch)
        # counted when handed to the publishers (committed, to go out in order): a reader
        # of the metrics after a reset or a step sees it; a message a newer one of its
        # loop replaced in a blocked lane is in `superseded`
        for mode, count in collections.Counter(m["mode"] for m in messages).items():
            self.metrics.updates_published.labels(mode).inc(count)

    def _lane(self, gateway: str | None) -> Lane:
        lane = self.lanes.get(gateway)
        if lane is None:
            with self._lanes_lock:
                lane = self.lanes.get(gateway)
                if lane is None:
                    lane = self.lanes[gateway] = Lane(gateway, self._send)
        return lane

    def _send(self, gateway: str | None, messages: list[dict]) -> None:
        """A lane's blocking part, on its own thread: no lock of the tuner is held."""
        if gateway is None:
            for message in messages:
                self.bus.publish(self.keys.gains(message["loop_id"]), orjson.dumps(message))
            return
        for i in range(0, len(messages), MAX_BATCH):
            payload = {"v": SCHEMA_VERSION, "gains": messages[i : i + MAX_BATCH]}
            self.bus.publish(self.keys.gateway_gains(gateway), orjson.dumps(payload))

    @property
    def superseded(self) -> int:
        """Gains messages replaced in their lane by a newer one before they went out."""
        return sum(lane.superseded for lane in list(self.lanes.values()))

    def _answer(self, query: zenoh.Query) -> None:
        key = str(query.key_expr)
        loop_id = self.keys.loop_id(key)
        if loop_id is not None and loop_id in self.table.slot_of:
            after_t = _after_t(query)
            if after_t is not None and not self._reflects(loop_id, after_t):
                deadline = time.monotonic() + AFTER_T_WAIT_S
                self._parked.setdefault(loop_id, []).append((after_t, deadline, query))
                return
            reply(query, encode(self._state(loop_id)))
            return
        if "*" in key:  # e.g. a reconnecting gateway asking for all its loops at once
            asked = zenoh.KeyExpr(key)
            for loop_id in list(self.table.slot_of):
                state_key = self.keys.state(loop_id)
                if asked.intersects(zenoh.KeyExpr(state_key)):
                    query.reply(state_key, encode(self._state(loop_id)), encoding=JSON)
            query.drop()
            return
        reply(query, encode(ErrorReply(loop_id=loop_id or key, error="unknown loop")), error=True)

    def _reflects(self, loop_id: str, after_t: float) -> bool:
        t = self.table.last_t[self.table.slot(loop_id)]
        return not math.isnan(t) and t >= after_t

    def _answer_parked(self) -> None:
        """Answer the parked ``after_t`` queries whose sample came, or whose wait is over
        (the reply's ``last_t`` then says the sample was not handled: rejected or lost)."""
        now = time.monotonic()
        for loop_id in list(self._parked):
            waiting = self._parked.pop(loop_id)
            if loop_id not in self.table.slot_of:  # deleted meanwhile
                for _, _, query in waiting:
                    error = ErrorReply(loop_id=loop_id, error="unknown loop")
                    with contextlib.suppress(zenoh.ZError):  # the querier may be gone
                        reply(query, encode(error), error=True)
                continue
            still = []
            for after_t, deadline, query in waiting:
                if now >= deadline or self._reflects(loop_id, after_t):
                    with contextlib.suppress(zenoh.ZError):  # the querier may be gone
                        reply(query, encode(self._state(loop_id)))
                else:
                    still.append((after_t, deadline, query))
            if still:
                self._parked[loop_id] = still

    def _answer_gateway(self, query: zenoh.Query) -> None:
        """One StateBatch with every loop registered with the gateway in the key."""
        gateway = self.keys.gateway_id(str(query.key_expr))
        if gateway is None:
            error = ErrorReply(loop_id=str(query.key_expr), error="not a gateway's state key")
            reply(query, encode(error), error=True)
            return
        tb = self.table
        states = [
            self._state(loop_id) for loop_id, s in tb.slot_of.items() if tb.gateways[s] == gateway
        ]
        batch = StateBatch(
            gateway=gateway, instance_id=self.settings.instance_id, epoch=self.epoch, states=states
        )
        reply(query, encode(batch))

    def _state(self, loop_id: str) -> StateReply:
        tb = self.table
        s = tb.slot(loop_id)
        return StateReply(
            loop_id=loop_id,
            kp=float(tb.kp[s]),
            ki=float(tb.ki[s]),
            mode=tb.mode_of(s),
            status=tb.status(s, time.time()),
            seq=int(tb.seq[s]),
            last_t=_finite(tb.last_t[s]),
            instance_id=self.settings.instance_id,
            epoch=self.epoch,
            rl_period_s=_finite(tb.period[s]),
            next_due_t=_finite(tb.next_due[s]),
            gateway=tb.gateways[s],
        )

    def _overload(self, item: Item, why: str) -> None:
        """A message the bus callback did not queue (a Zenoh thread: never blocks)."""
        kind, key = item[0], item[1]
        if kind is Kind.query or kind is Kind.gateway_query:
            self.queries_dropped += 1  # not a sample: no sample counter
            self._failure_log.warning("query", f"input queue full: state query {key!r} dropped")
            with contextlib.suppress(zenoh.ZError):
                item[2].drop()  # the querier gets no reply rather than waiting its timeout
            return
        reason = RejectReason.too_large if why == "too_large" else RejectReason.overload
        detail = f"{kind.name} message dropped unread ({why})"
        self.metrics.reject(reason, None, detail)
        self.metrics.samples_received.inc()  # after its counter, as in _handle

    # -- admin operations (the REST API) ----------------------------------------------
    def loop_ids(self) -> list[str]:
        with self.table.lock:
            return list(self.table.slot_of)

    def _known(self, loop_id: str) -> None:
        if loop_id not in self.table.slot_of:
            raise UnknownLoop(loop_id)

    def refresh_status_counts(self) -> None:
        """Loops per status into the metrics (statuses change with time: done per scrape)."""
        with self.table.lock:
            counts = self.table.status_counts(time.time())
            monitor = views.monitor_summary(self.table)
        self.metrics.set_status_counts(counts)
        self.metrics.set_monitor(*monitor)

    def view(self, loop_id: str) -> LoopView:
        with self.table.lock:
            self._known(loop_id)
            return self.table.view(loop_id, time.time())

    def views(self, offset: int, limit: int) -> LoopsPage:
        """A page of loops in registration order; parsed outside the table lock."""
        with self.engine.lock:
            total = len(self.engine)
            raw = self.engine.raw_views(offset, limit)
        items = [view.parse() for view in raw]
        return LoopsPage(items=items, total=total, offset=offset, limit=limit)

    def register(self, config: LoopConfig) -> LoopView:
        wall = time.time()
        with self.table.lock:
            if config.id in self.table.slot_of:
                raise Conflict(f"loop {config.id!r} already registered")
            self._insert([config], wall)
            return self.table.view(config.id, wall)

    def register_many(self, configs: list[LoopConfig]) -> list[str]:
        """Register several loops at once, all or none (Conflict if any id is taken)."""
        wall = time.time()
        ids = [c.id for c in configs]
        if len(set(ids)) != len(ids):
            raise Conflict("duplicate loop ids in the request")
        with self.table.lock:
            taken = [i for i in ids if i in self.table.slot_of]
            if taken:
                raise Conflict(f"loops already registered: {taken[:5]!r}")
            self._insert(configs, wall)
        _freeze_survivors()
        return ids

    def _insert(self, configs: list[LoopConfig], wall: float) -> None:
        """Store and add new loops, each continuing the seq of an earlier loop of its id."""
        last = self.store.last_seqs([c.id for c in configs])
        seqs = [last.get(c.id, 0) for c in configs]
        audit = [_registered(c, wall, seq) for c, seq in zip(configs, seqs, strict=True)]
        with _taken_in_store():
            self.store.insert_loops(configs, audit, seqs)
        for config, seq in zip(configs, seqs, strict=True):
            self.engine.register(config, seq=seq, wall=wall)
        self.metrics.set_loop_counts(self.table.mode_counts())

    def patch(self, loop_id: str, patch: LoopPatch, actor: str = "api") -> LoopView:
        """ValueError if the patch makes the bounds inconsistent; ``actor`` (the REST API,
        or ``ui:<name>`` from the console) is recorded in the audit row's detail."""
        wall = time.time()
        with self.table.lock:
            self._known(loop_id)
            s = self.table.slot(loop_id)
            config = patch.apply(self.table.configs[loop_id])
            gains = (float(self.table.kp[s]), float(self.table.ki[s]))
            self.store.update_config(
                config,
                audit_row(
                    loop_id, wall, None, int(self.table.seq[s]), config.mode.value, "patched",
                    gains, gains, _with_actor(patch.model_dump_json(exclude_unset=True), actor),
                ),
            )  # fmt: skip
            self.table.reconfigure(config)
            self.metrics.set_loop_counts(self.table.mode_counts())
            return self.table.view(loop_id, wall)

    def identify(self, loop_id: str) -> LoopView:
        """``POST /loops/{id}/identify``: identification from scratch (the identified
        scaling is dropped; a hint-free loop stops tuning until a new model is confident).
        StoreUnavailable while commits fail."""
        wall = time.time()
        with self.table.lock:
            self._known(loop_id)
            if self.store_failure is not None:
                raise StoreUnavailable(self.store_failure)
            self.engine.identify(loop_id, wall)
            self._commit(None)  # its audit row
            self._write_snapshot([loop_id])  # identification state is in the snapshot
            return self.table.view(loop_id, wall)

    def reset(self, loop_id: str, actor: str = "api") -> LoopView:
        """Zero hidden state and integral; the registered gains, published unless the loop
        is frozen (see :meth:`LoopTable.reset`). StoreUnavailable while commits fail."""
        wall = time.time()
        with self.table.lock:
            self._known(loop_id)
            if self.store_failure is not None:
                raise StoreUnavailable(self.store_failure)
            self._commit(self.engine.reset(loop_id, wall, actor=actor))
            return self.table.view(loop_id, wall)

    def delete(self, loop_id: str) -> None:
        wall = time.time()
        with self.table.lock:
            self._known(loop_id)
            s = self.table.slot(loop_id)
            gains = (float(self.table.kp[s]), float(self.table.ki[s]))
            mode = self.table.mode_of(s).value
            self.store.delete_loop(
                loop_id,
                audit_row(
                    loop_id, wall, None, int(self.table.seq[s]), mode, "deleted", gains, None
                ),
            )
            self.engine.remove(loop_id)
            self.recent.forget(loop_id)
            self.metrics.set_loop_counts(self.table.mode_counts())

    def history(self, loop_id: str, offset: int, limit: int) -> HistoryPage:
        """Also for a deleted loop, as long as it has history; each change with its
        verdict (:mod:`service.daemon.verdicts`)."""
        with self.table.lock:
            s = self.table.slot_of.get(loop_id)
            judged = None if s is None else int(self.table.v_seq[s])
        if offset + limit <= SCAN:  # the newer rows hold the verdicts of the page's
            total, items = self.store.history(loop_id, 0, offset + limit)
            annotate(items, judged)
            items = items[offset:]
        else:
            total, items = self.store.history(loop_id, offset, limit)
            annotate(items, judged)
        if not total and s is None:
            raise UnknownLoop(loop_id)
        return HistoryPage(items=items, total=total, offset=offset, limit=limit)

    def performance(self, loop_id: str) -> Performance:
        with self.table.lock:
            self._known(loop_id)
            return self.engine.performance(loop_id)

    def rollback(self, loop_id: str, actor: str = "api") -> LoopView:
        """Restore the last-good gains now (auto: published; advisory: proposed).
        Conflict when there is nothing to restore or the mode publishes nothing."""
        return self._decide(loop_id, lambda wall: self.engine.rollback(loop_id, wall, actor))

    def accept(self, loop_id: str, seq: int, actor: str = "api") -> LoopView:
        """Accept an advisory loop's pending proposal ``seq``: published as an ``auto``
        message for the gateway to apply. Conflict if ``seq`` is not the pending one."""
        return self._decide(loop_id, lambda wall: self.engine.accept(loop_id, seq, wall, actor))

    def reject(self, loop_id: str, seq: int, actor: str = "api") -> LoopView:
        """Reject an advisory loop's pending proposal ``seq`` (recorded, nothing sent)."""
        return self._decide(loop_id, lambda wall: self.engine.reject(loop_id, seq, wall, actor))

    def _decide(self, loop_id: str, decide: Callable[[float], StepResult | None]) -> LoopView:
        """An operator's decision: committed (and snapshotted) before it is published."""
        wall = time.time()
        with self.table.lock:
            self._known(loop_id)
            if self.store_failure is not None:
                raise StoreUnavailable(self.store_failure)
            try:
                result = decide(wall)
            except ValueError as exc:
                raise Conflict(str(exc)) from None
            self._commit(result)
            return self.table.view(loop_id, wall)


def _finite(x: float) -> float | None:
    return None if math.isnan(x) else float(x)


def _after_t(query: zenoh.Query) -> float | None:
    """The query's ``after_t`` parameter (None: absent or not a finite number)."""
    try:
        raw = query.parameters.get("after_t")
    except Exception:  # noqa: BLE001 - a malformed selector is no parameter
        return None
    if raw is None:
        return None
    try:
        value = float(raw)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


@contextlib.contextmanager
def _taken_in_store():
    """An id free in the table but taken in the store is a row that failed to load."""
    try:
        yield
    except sqlite3.IntegrityError:
        raise Conflict("loop id taken by a stored loop that failed to load (see the log)") from None


def _registered(config: LoopConfig, wall: float, seq: int) -> AuditRow:
    """The audit entry of a registration: no old gains, the registered ones as new."""
    return audit_row(
        config.id, wall, None, seq, config.mode.value, "registered",
        None, (config.kp, config.ki), config.model_dump_json(),
    )  # fmt: skip


def _with_actor(detail: str, actor: str) -> str:
    """A JSON object's text with the ``actor`` key added (audit details of changes)."""
    return orjson.dumps({**orjson.loads(detail), "actor": actor}).decode()
