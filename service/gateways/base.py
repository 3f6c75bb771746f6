"""The plant side of the pitune bus: what a DCS gateway does, over Zenoh.

A gateway (the plant simulator here, a real DCS gateway in
``deploy/examples/dcs_gateway.py``) follows ``docs/protocol.md``:

* it publishes one :class:`~service.wire.protocol.Sample` per loop and DCS scan on
  ``{prefix}/loops/{id}/sample`` with ``CongestionControl.BLOCK`` (never dropped); with a
  ``gateway_id``, :meth:`Gateway.publish_scan` sends a scan as one
  :class:`~service.wire.protocol.SampleColumns` on ``{prefix}/gateways/{gateway_id}/samples``
  while a tuner subscribes to it (revision 4: in a cluster only the member owning this
  gateway's loops does, so no other member decodes them), per loop otherwise, and per
  loop always for a loop whose state reply does not name this gateway (registered
  without it: the tuner rejects its samples on the gateway's key as ``wrong_gateway``);
* it receives :class:`~service.wire.protocol.GainsMessage` on ``{prefix}/loops/*/gains``
  and, with a ``gateway_id``, :class:`~service.wire.protocol.GainsBatch` on
  ``{prefix}/gateways/{gateway_id}/gains`` (loops registered with that gateway);
* it orders a loop's gains messages and state replies by ``(epoch, seq)`` and drops one
  that is not above the last it took for the loop (a duplicate, a late arrival, or a
  late message of a tuner instance since replaced, on the same store or a fresh one);
  messages without ``epoch`` (tuners of protocol revision 1) fall back to the seq rule
  per tuner ``instance_id``;
* it watches the tuners' liveliness tokens ``{prefix}/tuners/*`` and, whenever one
  appears (a tuner started, or this gateway (re)connected), asks for the state of its
  loops and takes the gains it missed while away: with a ``gateway_id``, one
  ``{prefix}/gateways/{gateway_id}/state`` query answered by one
  :class:`~service.wire.protocol.StateBatch` (loops not in it, registered without that
  gateway, are asked one by one; a tuner without that queryable is asked
  ``{prefix}/loops/*/state``); without, ``{prefix}/loops/*/state``;
* it reports in each sample ``applied_seq``, the seq of the last update the DCS applied
  to the loop in the current epoch (:meth:`Gateway.applied`; 0 while it applied none of
  it), so the tuner never takes a gateway lagging behind its updates for an operator's
  change;
* it keeps each loop's RL period and next due time from the state replies, for an
  "update overdue" watchdog (:meth:`Gateway.overdue`).

Zenoh callbacks run on Zenoh's threads and must never block: they only queue the raw
payloads, and the gateway's own loop validates and applies them between scans
(:meth:`Gateway.gains`; the DCS's PID blocks are not thread-safe either).

Messages are the pydantic models of :mod:`service.wire.protocol`, the single source of truth
for the wire format.
"""

from __future__ import annotations

import logging
import queue
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import Enum

import zenoh
from pydantic import ValidationError

from service.wire.protocol import (
    ENCODING,
    EPOCH_AHEAD_MS,
    MAX_BATCH,
    PUBLISHED_MODES,
    BatchedSample,
    GainsBatch,
    GainsMessage,
    Keys,
    Mode,
    Sample,
    SampleColumns,
    StateBatch,
    StateReply,
    encode,
)

log = logging.getLogger("pitune.gateway")
SAMPLE_CONGESTION = zenoh.CongestionControl.BLOCK
"""Samples are never dropped under congestion (docs/protocol.md, Samples)."""
STATE_QUERY_TIMEOUT_S = 10.0
IMPLAUSIBLE_LOG_S = 60.0
"""Least time between two log lines about gains dropped for an implausible epoch."""


class Source(Enum):
    """Where a gains update came from."""

    gains = "gains"
    """A per-loop :class:`GainsMessage`."""
    batch = "batch"
    """An item of a :class:`GainsBatch`."""
    state = "state"
    """A :class:`StateReply` (state query on (re)connect): gains published while away."""
    state_batch = "state_batch"
    """A :class:`StateBatch`: the state of a gateway's loops in one reply."""


@dataclass(frozen=True)
class Update:
    """Gains for one loop that passed the sequence rule, to apply if ``mode`` is auto."""

    loop_id: str
    kp: float
    ki: float
    mode: Mode
    seq: int
    instance_id: str
    source: Source
    epoch: int | None = None


@dataclass
class GainsInbox:
    """Raw gains payloads in, validated updates out, duplicates and late ones dropped.

    The sequence rule of docs/protocol.md, per loop: a message whose ``(epoch, seq)`` is
    not above the highest one taken for that loop is a duplicate, arrived out of order,
    or comes from a tuner instance since replaced, and is dropped. ``advisory`` messages
    and ``auto`` state replies count too (``seq`` increases per loop whatever the mode),
    so a late ``auto`` message never undoes a newer update; other state replies change
    nothing. A message without ``epoch`` (a tuner of
    revision 1) is judged against the messages of its own ``instance_id`` only.
    """

    loops: frozenset[str] | None = None
    """The loops of interest (None: all); messages of other loops are ignored."""
    invalid: int = 0
    stale: int = 0
    implausible: int = 0
    """Messages dropped for an epoch far ahead of this host's clock (:data:`EPOCH_AHEAD_MS`);
    logged as an error at most every IMPLAUSIBLE_LOG_S."""
    _implausible_log_at: float = 0.0
    """Monotonic time before which no further drop for an implausible epoch is logged."""
    _raw: queue.SimpleQueue = field(default_factory=queue.SimpleQueue)
    _last: dict[tuple[str, str], int] = field(default_factory=dict)
    """Per (loop, instance), the highest seq taken of messages without an epoch (their
    rule); messages with one need only :attr:`_order` and :attr:`_newest`, an entry per
    loop, so tuner restarts add nothing (an entry per restart and loop was 22 MB after
    100 restarts of 2,000 loops)."""
    _order: dict[str, tuple[int, int]] = field(default_factory=dict)
    """Per loop, the highest (epoch, seq) taken."""
    _newest: dict[str, tuple[str, int]] = field(default_factory=dict)
    """Per loop, the instance and seq of the newest message with an epoch taken: a
    message without one from that instance is judged against it too."""
    supervision: dict[str, StateReply] = field(default_factory=dict)
    """The last state reply of each loop (RL period, next due time, status, gateway)."""
    batch_replies: list[StateBatch] = field(default_factory=list)
    """StateBatch replies drained and not yet looked at by the :class:`Gateway`."""
    update_t: dict[str, float] = field(default_factory=dict)
    """Plant time of the newest gains message taken per loop (reason agent)."""

    def put_raw(self, source: Source, payload: bytes) -> None:
        """Queue a payload (the only thing a Zenoh callback may do)."""
        self._raw.put((source, payload))

    def drain(self) -> list[Update]:
        """Updates received since the last call, in arrival order, after the seq rule."""
        out: list[Update] = []
        while True:
            try:
                source, payload = self._raw.get_nowait()
            except queue.Empty:
                return out
            try:
                if source is Source.gains:
                    messages = [GainsMessage.model_validate_json(payload)]
                elif source is Source.batch:
                    messages = GainsBatch.model_validate_json(payload).gains
                elif source is Source.state_batch:
                    batch = StateBatch.model_validate_json(payload)
                    self.batch_replies.append(batch)
                    messages = batch.states
                else:
                    messages = [StateReply.model_validate_json(payload)]
            except ValidationError:
                self.invalid += 1
                continue
            for msg in messages:
                update = self.take(msg, source)
                if update is not None:
                    out.append(update)

    def take(self, msg: GainsMessage | StateReply, source: Source) -> Update | None:
        """Apply the sequence rule to one message: the update, or None if dropped."""
        if self.loops is not None and msg.loop_id not in self.loops:
            return None
        if isinstance(msg, StateReply):
            self.supervision[msg.loop_id] = msg
            if msg.seq == 0 or msg.mode is not Mode.auto:
                return None  # no gains published yet, or none to apply (docs/protocol.md)
        if msg.epoch is not None and msg.epoch > time.time() * 1000.0 + EPOCH_AHEAD_MS:
            self._implausible(msg)  # taken, it would put every real update below it
            return None
        state = source in (Source.state, Source.state_batch)
        key = (msg.loop_id, msg.instance_id)
        if msg.epoch is not None:
            newer = (msg.epoch, msg.seq) > self._order.get(msg.loop_id, (0, 0))
        else:
            last = self._last.get(key)
            instance, seq = self._newest.get(msg.loop_id, (None, 0))
            if instance == msg.instance_id:
                last = max(seq, last or 0)
            newer = last is None or msg.seq > last
        if not newer:
            if not state:  # a state reply of known gains is no news
                self.stale += 1
            return None
        if msg.epoch is None:
            self._last[key] = msg.seq
        if isinstance(msg, GainsMessage) and msg.reason == "agent":
            self.update_t[msg.loop_id] = msg.t
        if msg.epoch is not None:
            self._order[msg.loop_id] = (msg.epoch, msg.seq)
            self._newest[msg.loop_id] = (msg.instance_id, msg.seq)
        return Update(
            msg.loop_id, msg.kp, msg.ki, Mode(msg.mode), msg.seq, msg.instance_id, source,
            msg.epoch,
        )  # fmt: skip

    def _implausible(self, msg: GainsMessage | StateReply) -> None:
        """Count a message dropped for its epoch; an error in the log at most every
        IMPLAUSIBLE_LOG_S: while it lasts, the loops' gains are not applied."""
        self.implausible += 1
        now = time.monotonic()
        if now < self._implausible_log_at:
            return
        self._implausible_log_at = now + IMPLAUSIBLE_LOG_S
        log.error(
            "gains of %s from %r DROPPED: epoch %d is %.1f h ahead of this host's clock "
            "(%d dropped so far); is this host's clock behind, or was the tuner's ahead "
            "(docs/deploy.md, Clocks)?",
            msg.loop_id, msg.instance_id, msg.epoch,
            (msg.epoch - time.time() * 1000.0) / 3.6e6, self.implausible,
        )  # fmt: skip

    def current_epoch(self, loop_id: str) -> int | None:
        """The epoch of the newest message taken for the loop (None: none with one)."""
        order = self._order.get(loop_id)
        return None if order is None else order[0]


class Gateway:
    """Publishes the samples of the given loops and collects the gains addressed to them.

    ``gateway_id``: also receive the :class:`GainsBatch` messages of the loops registered
    with ``"gateway": gateway_id``. Call :meth:`close` on every exit path (a callback
    subscriber left declared hangs the interpreter at exit).
    """

    def __init__(
        self,
        session: zenoh.Session,
        loop_ids: Iterable[str],
        keys: Keys,
        *,
        gateway_id: str | None = None,
    ) -> None:
        self.session = session
        self.keys = keys
        self.gateway_id = gateway_id
        loop_ids = list(loop_ids)
        self.loop_ids = frozenset(loop_ids)
        self.inbox = GainsInbox(loops=self.loop_ids)
        self._applied: dict[str, tuple[int | None, int]] = {}
        self._batch_answered = False
        self.tuners: set[str] = set()
        """Key expressions of the tuners' liveliness tokens seen alive."""
        self._events: queue.SimpleQueue[tuple[zenoh.SampleKind, str]] = queue.SimpleQueue()
        self._publishers = {}
        self._entities: list = []
        self._batches = None
        """Publisher of this gateway's samples key (with a ``gateway_id``)."""
        self._unheard: set[str] = set()
        """Loops whose samples went on their own keys with no subscriber known there."""
        try:
            for loop_id in loop_ids:
                self._publishers[loop_id] = session.declare_publisher(
                    keys.sample(loop_id), encoding=ENCODING, congestion_control=SAMPLE_CONGESTION
                )
            self._entities.append(
                session.declare_subscriber(keys.all_gains, self._queue(Source.gains))
            )
            if gateway_id is not None:
                self._entities.append(
                    session.declare_subscriber(
                        keys.gateway_gains(gateway_id), self._queue(Source.batch)
                    )
                )
                self._batches = session.declare_publisher(
                    keys.gateway_samples(gateway_id),
                    encoding=ENCODING,
                    congestion_control=SAMPLE_CONGESTION,
                )
                self._entities.append(self._batches)
            # history: the tokens of tuners already up are delivered at once
            self._entities.append(
                session.liveliness().declare_subscriber(
                    keys.all_tuners, self._on_tuner, history=True
                )
            )
        except BaseException:
            self.close()
            raise

    def _queue(self, source: Source):
        def on_sample(sample: zenoh.Sample) -> None:
            self.inbox.put_raw(source, sample.payload.to_bytes())

        return on_sample

    def _on_tuner(self, sample: zenoh.Sample) -> None:
        self._events.put((sample.kind, str(sample.key_expr)))

    def _on_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:  # error replies (unknown loop) change nothing
            self.inbox.put_raw(Source.state, reply.ok.payload.to_bytes())

    def _on_batch_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            self._batch_answered = True
            self.inbox.put_raw(Source.state_batch, reply.ok.payload.to_bytes())

    def _batch_query_done(self) -> None:
        if not self._batch_answered:  # a tuner of revision 1: no gateway queryable
            self._events.put((None, "fallback"))

    def query_state(self) -> None:
        """Ask the tuner for the state of this gateway's loops; the replies arrive as
        :class:`Update` s from :meth:`gains` (non-blocking). With a ``gateway_id``, one
        query of the gateway's state key (one StateBatch reply); else every loop's."""
        if self.gateway_id is None:
            self._query_all()
            return
        self._batch_answered = False
        self.session.get(
            self.keys.gateway_state(self.gateway_id),
            zenoh.handlers.Callback(self._on_batch_reply, self._batch_query_done),
            timeout=STATE_QUERY_TIMEOUT_S,
        )

    def _query_all(self) -> None:
        self.session.get(self.keys.all_states, self._on_reply, timeout=STATE_QUERY_TIMEOUT_S)

    def _query_missing(self) -> None:
        """Loops of this gateway a StateBatch did not cover: asked one by one."""
        while self.inbox.batch_replies:
            batch = self.inbox.batch_replies.pop(0)
            covered = {s.loop_id for s in batch.states}
            for loop_id in sorted(self.loop_ids - covered):
                self.session.get(
                    self.keys.state(loop_id), self._on_reply, timeout=STATE_QUERY_TIMEOUT_S
                )

    def _watch_tuners(self) -> None:
        while True:
            try:
                kind, key = self._events.get_nowait()
            except queue.Empty:
                return
            if kind is None:  # the gateway query went unanswered
                log.info("no StateBatch reply: asking every loop's state")
                self._query_all()
            elif kind == zenoh.SampleKind.PUT:
                log.info("tuner up: %s; asking the state of the loops", key)
                self.tuners.add(key)
                self.query_state()
            else:
                self.tuners.discard(key)
                if not self.tuners:
                    log.warning("no tuner up (%s left): no gains until one is back", key)

    @property
    def tuner_up(self) -> bool:
        """Whether a tuner's liveliness token is present (as of the last :meth:`gains`)."""
        return bool(self.tuners)

    def publish(self, loop_id: str, sample: Sample) -> None:
        """Publish ``sample``; without an ``applied_seq`` of its own it reports the last
        update :meth:`applied` marked for the loop in the current epoch."""
        self._publishers[loop_id].put(encode(self._reported(loop_id, sample)))

    def publish_scan(self, samples: dict[str, Sample]) -> None:
        """Publish one scan's samples (loop id -> sample, ``applied_seq`` as
        :meth:`publish`). With a ``gateway_id`` and a tuner subscribed to this gateway's
        samples key (revision 4), as SampleColumns messages there (revision 6: decoded ~5x
        cheaper than a SampleBatch); else (no gateway id, a
        tuner of an earlier revision, or a cluster between two owners of this gateway)
        one message per loop, which every tuner hears."""
        batches = self._batches
        ours = {} if batches is None or not batches.matching_status.matching else {
            loop_id: sample for loop_id, sample in samples.items() if self._ours(loop_id)
        }  # fmt: skip
        solo = samples.keys() - ours.keys()
        for loop_id in solo:
            self.publish(loop_id, samples[loop_id])
        if batches is not None:
            self._check_heard(solo)
        items = [
            BatchedSample(loop_id=loop_id, **self._reported(loop_id, sample).model_dump())
            for loop_id, sample in ours.items()
        ]
        for i in range(0, len(items), MAX_BATCH):
            batches.put(encode(SampleColumns.of(items[i : i + MAX_BATCH])))

    def _check_heard(self, solo: set[str]) -> None:
        """Log when samples sent on their loops' own keys start (and stop) going unheard
        while a tuner is up: a declared publisher with no subscriber known drops them on
        this side, silently. That is how a Zenoh user confined to its gateway's keys (no
        per-loop keys: docs/deploy.md) loses them; with the shared user the tuner
        subscribes there and nothing is logged. Once per change, not per scan."""
        if not self.tuners:
            return  # nothing is heard then, as its own warning says
        unheard = {i for i in solo if not self._publishers[i].matching_status.matching}
        new = sorted(unheard - self._unheard)
        if new:
            log.warning(
                "samples of %d loop(s) dropped (%s): sent on their own keys %s (%s), where "
                "this gateway's Zenoh user knows no subscriber: a user confined to gateway "
                "%s's keys may not use them (docs/deploy.md, Zenoh passwords)",
                len(new), ", ".join(new[:5]) + (", ..." if len(new) > 5 else ""),
                self.keys.sample("{id}"), self._why_solo(), self.gateway_id,
            )  # fmt: skip
        elif self._unheard and not unheard:
            log.info("samples heard again: every loop's key has a subscriber or is batched")
        self._unheard = unheard

    def _why_solo(self) -> str:
        if not self._batches.matching_status.matching:
            return f"no tuner subscribes to {self.keys.gateway_samples(self.gateway_id)}"
        return (
            f"no state reply names them as gateway {self.gateway_id}'s: not yet, or they "
            "are registered without it"
        )

    def _ours(self, loop_id: str) -> bool:
        """The tuner's state reply says the loop is registered with this gateway (until
        one comes, its samples go on the loop's own key, which every tuner takes)."""
        state = self.inbox.supervision.get(loop_id)
        return state is not None and state.gateway == self.gateway_id

    def _reported(self, loop_id: str, sample: Sample) -> Sample:
        if sample.applied_seq is None:
            seq = self.applied_seq(loop_id)
            if seq is not None:
                return sample.model_copy(update={"applied_seq": seq})
        return sample

    def applied(self, update: Update) -> None:
        """Record that the DCS applied ``update`` (reported as ``applied_seq``)."""
        self._applied[update.loop_id] = (update.epoch, update.seq)

    def applied_seq(self, loop_id: str) -> int | None:
        """The seq of the last update applied to the loop within the epoch of the newest
        update taken (seqs of another epoch mean nothing to the tuner now); 0 if none of
        that epoch is applied yet: left out, a gateway lagging behind its first update
        would report the old gains as an operator's change (an integrator's review,
        session 40); None before any update is taken (or, from a tuner of revision 1,
        whose messages carry no epoch, before one is applied)."""
        epoch = self.inbox.current_epoch(loop_id)
        applied = self._applied.get(loop_id)
        if applied is not None and applied[0] == epoch:
            return applied[1]
        return None if epoch is None else 0

    def overdue(self, loop_id: str, plant_t: float, periods: float = 2.0) -> bool:
        """Whether an update of a loop the tuner last said was ``tuning`` is overdue at
        plant time ``plant_t``: more than ``periods`` RL periods past the later of its
        next due time (state reply) and its last update. Ask the state again then
        (:meth:`query_state`): a quiet, stale or manual loop gets no updates. A loop in a
        mode that gets no messages (shadow, frozen) is never overdue."""
        state = self.inbox.supervision.get(loop_id)
        if state is None or state.status != "tuning" or not state.rl_period_s:
            return False
        if state.mode not in PUBLISHED_MODES:
            return False
        due = max(
            state.next_due_t if state.next_due_t is not None else -float("inf"),
            self.inbox.update_t.get(loop_id, -float("inf")) + state.rl_period_s,
        )
        return plant_t > due + periods * state.rl_period_s

    def gains(self) -> list[Update]:
        """Updates for this gateway's loops received since the last call, after the
        sequence rule; ``mode`` says whether to apply them (auto) or only show them."""
        self._watch_tuners()
        updates = self.inbox.drain()
        self._query_missing()
        return updates

    def close(self) -> None:
        """Undeclare subscribers and publishers (idempotent); the session is the caller's."""
        for entity in [*reversed(self._entities), *self._publishers.values()]:
            try:
                entity.undeclare()
            except zenoh.ZError as exc:  # already gone with a closed session
                log.debug("undeclare failed: %s", exc)
        self._entities, self._publishers = [], {}
