"""The plant side of the pitune bus: what a DCS gateway does, over Zenoh.

A gateway publishes one :class:`~service.protocol.Sample` per loop and DCS scan on
``{prefix}/loops/{id}/sample`` and subscribes to ``{prefix}/loops/*/gains``. Gains
messages arrive on a Zenoh thread; the callback only queues the raw payload, and the
plant's own loop validates and applies them between scans (a callback must never block
the Zenoh runtime, and the PI blocks are not thread-safe).

Messages are the pydantic models of :mod:`service.protocol`, the single source of truth
for the wire format.
"""

from __future__ import annotations

import json
import queue
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import zenoh
from pydantic import ValidationError

from service.protocol import ENCODING, GainsMessage, Keys, Sample, encode


def session_config(
    *,
    mode: str | None = None,
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    config_file: str | None = None,
) -> zenoh.Config:
    """A Zenoh config: from ``config_file`` (JSON5) if given, then the explicit overrides.

    ``mode`` None keeps the file's mode (Zenoh's default, peer, without a file).
    Multicast scouting is off whenever endpoints are given explicitly, so processes on
    one host never find strangers on the network.
    """
    config = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    if mode:
        config.insert_json5("mode", json.dumps(mode))
    if connect:
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen:
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect or listen:
        config.insert_json5("scouting/multicast/enabled", "false")
    return config


@dataclass
class GainsInbox:
    """Validated gains messages, newest per loop, with duplicates and stale ones dropped.

    Sequence numbers increase across tuner restarts, so a message whose ``seq`` is not
    above the last applied one from the same tuner instance is a duplicate or arrived
    out of order. A different instance (a replaced tuner with a fresh store) is trusted.
    """

    invalid: int = 0
    stale: int = 0
    _raw: queue.SimpleQueue = field(default_factory=queue.SimpleQueue)
    _last: dict[str, tuple[str, int]] = field(default_factory=dict)

    def put_raw(self, payload: bytes) -> None:
        self._raw.put(payload)

    def drain(self) -> list[GainsMessage]:
        """Messages received since the last call, in arrival order, newest-only filtered."""
        out = []
        while True:
            try:
                payload = self._raw.get_nowait()
            except queue.Empty:
                return out
            try:
                msg = GainsMessage.model_validate_json(payload)
            except ValidationError:
                self.invalid += 1
                continue
            last = self._last.get(msg.loop_id)
            if last is not None and last[0] == msg.instance_id and msg.seq <= last[1]:
                self.stale += 1
                continue
            self._last[msg.loop_id] = (msg.instance_id, msg.seq)
            out.append(msg)


class Gateway:
    """Publishes samples of the given loops and collects the gains addressed to them."""

    def __init__(self, session: zenoh.Session, loop_ids: Iterable[str], keys: Keys) -> None:
        self.keys = keys
        self.inbox = GainsInbox()
        self._publishers = {
            loop_id: session.declare_publisher(keys.sample(loop_id), encoding=ENCODING)
            for loop_id in loop_ids
        }
        self._subscriber = session.declare_subscriber(keys.all_gains, self._on_gains)

    def _on_gains(self, sample: zenoh.Sample) -> None:
        self.inbox.put_raw(sample.payload.to_bytes())

    def publish(self, loop_id: str, sample: Sample) -> None:
        self._publishers[loop_id].put(encode(sample))

    def gains(self) -> list[GainsMessage]:
        """Gains messages for this gateway's loops received since the last call."""
        return [m for m in self.inbox.drain() if m.loop_id in self._publishers]

    def close(self) -> None:
        self._subscriber.undeclare()
        for publisher in self._publishers.values():
            publisher.undeclare()
