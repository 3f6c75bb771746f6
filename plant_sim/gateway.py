"""The plant side of the pitune bus: what a DCS gateway does, over Zenoh.

A gateway (the plant simulator here, a real DCS gateway in
``deploy/examples/dcs_gateway.py``) follows ``docs/protocol.md``:

* it publishes one :class:`~service.wire.protocol.Sample` per loop and DCS scan on
  ``{prefix}/loops/{id}/sample`` with ``CongestionControl.BLOCK`` (never dropped);
* it receives :class:`~service.wire.protocol.GainsMessage` on ``{prefix}/loops/*/gains``
  and, with a ``gateway_id``, :class:`~service.wire.protocol.GainsBatch` on
  ``{prefix}/gateways/{gateway_id}/gains`` (loops registered with that gateway);
* it drops a gains message whose ``seq`` is not above the last one it took for the
  same loop from the same tuner ``instance_id`` (a duplicate or a late arrival);
* it watches the tuners' liveliness tokens ``{prefix}/tuners/*`` and, whenever one
  appears (a tuner started, or this gateway (re)connected), asks
  ``{prefix}/loops/*/state`` and takes the gains of its ``auto`` loops whose ``seq``
  is newer than what it has: the updates it missed while away.

Zenoh callbacks run on Zenoh's threads and must never block: they only queue the raw
payloads, and the gateway's own loop validates and applies them between scans
(:meth:`Gateway.gains`; the DCS's PID blocks are not thread-safe either).

Messages are the pydantic models of :mod:`service.wire.protocol`, the single source of truth
for the wire format.
"""

from __future__ import annotations

import logging
import queue
from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import Enum

import zenoh
from pydantic import ValidationError

from service.wire.protocol import (
    ENCODING,
    GainsBatch,
    GainsMessage,
    Keys,
    Mode,
    Sample,
    StateReply,
    encode,
)

log = logging.getLogger("pitune.gateway")
SAMPLE_CONGESTION = zenoh.CongestionControl.BLOCK
"""Samples are never dropped under congestion (docs/protocol.md, Samples)."""
STATE_QUERY_TIMEOUT_S = 10.0


class Source(Enum):
    """Where a gains update came from."""

    gains = "gains"
    """A per-loop :class:`GainsMessage`."""
    batch = "batch"
    """An item of a :class:`GainsBatch`."""
    state = "state"
    """A :class:`StateReply` (state query on (re)connect): gains published while away."""


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


@dataclass
class GainsInbox:
    """Raw gains payloads in, validated updates out, duplicates and late ones dropped.

    The sequence rule of docs/protocol.md, per loop and tuner instance: a message whose
    ``seq`` is not above the highest one taken for that loop from the same
    ``instance_id`` is a duplicate or arrived out of order, and is dropped. ``advisory``
    messages and state replies count too (``seq`` increases per loop whatever the mode),
    so a late ``auto`` message never undoes a newer update. A different instance (a
    replaced tuner with a fresh store, whose ``seq`` starts again at 1) is judged
    against its own messages only.
    """

    loops: frozenset[str] | None = None
    """The loops of interest (None: all); messages of other loops are ignored."""
    invalid: int = 0
    stale: int = 0
    _raw: queue.SimpleQueue = field(default_factory=queue.SimpleQueue)
    _last: dict[tuple[str, str], int] = field(default_factory=dict)

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
        if isinstance(msg, StateReply) and (msg.seq == 0 or msg.mode is Mode.frozen):
            return None  # no gains published yet, or none to apply
        key = (msg.loop_id, msg.instance_id)
        last = self._last.get(key)
        if last is not None and msg.seq <= last:
            if source is not Source.state:  # a state reply of known gains is no news
                self.stale += 1
            return None
        self._last[key] = msg.seq
        return Update(msg.loop_id, msg.kp, msg.ki, Mode(msg.mode), msg.seq, msg.instance_id, source)


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
        loop_ids = list(loop_ids)
        self.inbox = GainsInbox(loops=frozenset(loop_ids))
        self.tuners: set[str] = set()
        """Key expressions of the tuners' liveliness tokens seen alive."""
        self._events: queue.SimpleQueue[tuple[zenoh.SampleKind, str]] = queue.SimpleQueue()
        self._publishers = {}
        self._entities: list = []
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

    def query_state(self) -> None:
        """Ask the tuner for the state of every loop; the replies of this gateway's loops
        arrive as :class:`Update` s from :meth:`gains` (non-blocking)."""
        self.session.get(self.keys.all_states, self._on_reply, timeout=STATE_QUERY_TIMEOUT_S)

    def _watch_tuners(self) -> None:
        while True:
            try:
                kind, key = self._events.get_nowait()
            except queue.Empty:
                return
            if kind == zenoh.SampleKind.PUT:
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
        self._publishers[loop_id].put(encode(sample))

    def gains(self) -> list[Update]:
        """Updates for this gateway's loops received since the last call, after the
        sequence rule; ``mode`` says whether to apply them (auto) or only show them."""
        self._watch_tuners()
        return self.inbox.drain()

    def close(self) -> None:
        """Undeclare subscribers and publishers (idempotent); the session is the caller's."""
        for entity in [*reversed(self._entities), *self._publishers.values()]:
            try:
                entity.undeclare()
            except zenoh.ZError as exc:  # already gone with a closed session
                log.debug("undeclare failed: %s", exc)
        self._entities, self._publishers = [], {}
