"""How the tuner worker delivers a step: commit first, then publish.

The table's pending gains and audit rows (and the verification state they change) are
committed to the store before any gains message goes out; while the store fails,
steps are held, unpublished, and retried every COMMIT_RETRY_S; failing for
``store_failure_exit_s`` ends the process for a supervisor to restart it from the store.

Publishing never holds the worker: committed gains go to a :class:`Lane` per
destination (one for the per-loop keys, one per gateway), each with its own thread
doing the blocking put, in order; past LANE_BOUND waiting messages a lane keeps only
the newest of each loop (gains are absolute and gateways drop older seqs), so it stays
bounded, and a stuck gateway delays only its own lane.
"""

from __future__ import annotations

import collections
import logging
import os
import time

import orjson

from service.daemon.lanes import Lane
from service.daemon.store_pg import Fenced
from service.engine.updates import StepResult
from service.wire.protocol import MAX_BATCH, MAX_MESSAGE_BYTES, SCHEMA_VERSION

log = logging.getLogger("pitune.tuner")
COMMIT_RETRY_S = 1.0
"""Seconds between attempts to commit while the store fails."""
EXIT_STORE_FAILED = 74
"""Exit status after ``store_failure_exit_s`` of failing commits (EX_IOERR)."""
IDENTIFICATION_OUTCOMES = frozenset(
    {"identified", "rescaled", "mismatch", "out_of_envelope", "in_envelope", "identify", "model",
     "refuted"}
)  # fmt: skip
"""Audit reasons of the engine's identification (counted per outcome; 'model': the first
tuning from an identified model; 'refuted': a model like one whose tuning rang, not used)."""


class Delivery:
    """Mixin of :class:`service.daemon.tuner.Tuner`: its worker commits and publishes each
    step through these; the lanes call :meth:`_send` on their own threads."""

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
            # each with the epoch its message goes out under (its state replies' epoch)
            rows = [(*g, self._row_epoch(g[3], g[2])) for g in gains]
            try:
                if self.cluster is None:
                    self.store.record_gains(rows, audit)
                else:
                    fence = self._fence({g[3] for g in gains} | {a[0] for a in audit})
                    self.store.record_gains(rows, audit, fence)
            except Fenced as exc:
                try:
                    self._fenced(exc, gains, audit)
                except Exception as err:  # noqa: BLE001 - the renewal failed: as below
                    self.table.requeue(gains, audit)
                    self.table.requeue_verify_dirty(dirty)
                    self._store_failed(err)
                    return
                self.table.requeue_verify_dirty(dirty)  # of the loops still ours
                self._commit(None)  # (leases renewed: the fence lets it through now)
                return
            except Exception as exc:  # sqlite3.Error, OSError, MemoryError: all the same
                self.table.requeue(gains, audit)
                self.table.requeue_verify_dirty(dirty)
                self._store_failed(exc)
                return
            self.epochs.update((row[3], (row[4], row[2])) for row in rows if row[4] is not None)
            # INFO per adoption, verdict, ..., rate-limited (gains: when published, below)
            self.metrics.events.audit(audit)
            self.metrics.verdict(audit)
        if dirty:
            # last-good gains, verdicts and proposals on disk before what follows from
            # them goes out: a SIGKILL after this keeps them (they resume on restart)
            if self.snapshot_writer is not None:  # their queued periodic rows are older
                self.snapshot_writer.discard(dirty)
            rows = self.table.snapshot(dirty)
            try:
                self.store.snapshot(rows, None if self.cluster is None else self._fence(dirty))
            except Fenced as exc:  # leases run out or lost since the commit: as above
                try:
                    self._fenced(exc, [], [])
                except Exception as err:  # noqa: BLE001 - as above
                    self.table.requeue_verify_dirty(dirty)
                    self._store_failed(err)
                    return
                self.table.requeue_verify_dirty(dirty)
                self._commit(None)
                return
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
            self._wake()  # a worker asleep until its next snapshot retries from now on
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
        publishable = self._publishable(result.messages(self.settings.instance_id), result.gateways)
        messages = [message for message, _ in publishable]
        by_gateway: dict[str | None, list[dict]] = collections.defaultdict(list)
        for message, gateway in publishable:
            by_gateway[gateway].append(message)
        for gateway, batch in by_gateway.items():
            self._lane(gateway).submit(batch)
        self.metrics.events.published(messages)  # INFO per update, rate-limited
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
        """A lane's blocking part, on its own thread: no lock of the tuner is held. In a
        cluster, nothing goes out once the leases may have run out (a paused member),
        checked before each put: a member paused in the middle of a batch of single
        messages had published the rest of it after its lease (a CI run, session 37).
        Nor do the messages of loops whose shards this member no longer holds: a renewal
        that found their leases taken (by the member waking, or by a commit refused,
        :meth:`_fenced`) took the shards off before it made the leases valid again; their
        new owner sends each loop's last message again (:meth:`_resend`). Each put checks
        that its loops' shards are still held under the tokens they were held under at
        the start: a member woken in the middle of a batch had its renewal make the
        leases valid again (for the shards still held) before the rest went out, and it
        may hold a lost shard again, under a new token, before the rest goes out (their
        loops' messages waiting in a lane are dropped with the loops,
        :meth:`~service.daemon.ownership.Ownership.drop_shards`)."""
        cluster = self.cluster
        if cluster is not None:
            tokens = {m["loop_id"]: cluster.token(m["loop_id"]) for m in messages}
        step = 1 if gateway is None else MAX_BATCH
        for i in range(0, len(messages), step):
            chunk = messages[i : i + step]
            if cluster is not None:
                if not cluster.may_publish():  # the messages left, counted
                    self.gains_fenced += len(messages) - i
                    return
                held = [m for m in chunk if tokens[m["loop_id"]] is not None]
                held = [m for m in held if cluster.token(m["loop_id"]) == tokens[m["loop_id"]]]
                self.gains_fenced += len(chunk) - len(held)
                chunk = held
            if gateway is None:
                for m in chunk:
                    self.bus.publish(self.keys.gains(m["loop_id"]), orjson.dumps(m))
            elif chunk:
                key = self.keys.gateway_gains(gateway)
                for payload in _within_size(chunk):
                    self.bus.publish(key, payload)

    @property
    def superseded(self) -> int:
        """Gains messages replaced in their lane by a newer one before they went out."""
        return sum(lane.superseded for lane in list(self.lanes.values()))


def _within_size(messages: list[dict]) -> list[bytes]:
    """``messages`` as GainsBatch payloads of at most MAX_MESSAGE_BYTES each, halved until
    they fit: 100,000 items of 64-character loop ids made 37 MiB, which the routers and
    gateways drop unread (their links take 33 MiB: deploy/zenoh/router.json5)."""
    payload = orjson.dumps({"v": SCHEMA_VERSION, "gains": messages})
    if len(payload) <= MAX_MESSAGE_BYTES or len(messages) == 1:
        return [payload]
    half = len(messages) // 2
    return _within_size(messages[:half]) + _within_size(messages[half:])
