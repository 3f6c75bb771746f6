"""The tuner's Zenoh side: session, sample subscribers, state queryable, liveliness token.

Zenoh callbacks run on Zenoh's threads and must never block, so they only copy the
key and payload into a bounded queue (a full queue drops the message and says so);
the tuner's worker thread does everything else, queries included, so a state reply
always reflects every sample received before the query.

A callback subscriber still declared when the interpreter exits hangs it (zenoh 1.10),
so :meth:`Bus.close` undeclares everything and closes the session; the tuner calls it
on every shutdown path.
"""

from __future__ import annotations

import logging
import queue
from collections.abc import Callable
from enum import IntEnum

import zenoh

from service.daemon.settings import Settings
from service.wire.protocol import Keys
from service.wire.session import session_config

log = logging.getLogger("pitune.bus")
JSON = zenoh.Encoding.APPLICATION_JSON
GAINS_CONGESTION = zenoh.CongestionControl.BLOCK
"""Gains are never dropped under congestion: the tuner assumes ``auto`` gains applied."""
GAINS_PRIORITY = zenoh.Priority.DATA_HIGH
"""Above the samples' default ``DATA``, so gains overtake sample traffic on a shared link
or router; below the ``INTERACTIVE_*`` lanes, which a 2 MB gains batch would hold up."""


class Kind(IntEnum):
    sample = 0
    batch = 1
    query = 2


Item = tuple[Kind, str, object]
"""(kind, key expression, payload bytes or the zenoh.Query)."""


def zenoh_config(settings: Settings) -> zenoh.Config:
    """Zenoh config: the JSON5 file if given, then the settings' mode and endpoints.

    Without a file, every setting applies (peer on loopback, no multicast scouting).
    With a file, only settings given explicitly (flag, environment, config) override it,
    so TLS and user/password sections of the file stay in charge.
    """
    explicit = None if settings.zenoh_config is None else settings.model_fields_set

    def given(field: str, value: object) -> object:
        return value if explicit is None or field in explicit else None

    return session_config(
        config_file=settings.zenoh_config,
        mode=given("zenoh_mode", settings.zenoh_mode),
        listen=given("zenoh_listen", settings.zenoh_listen),
        connect=given("zenoh_connect", settings.zenoh_connect),
        multicast_scouting=given("zenoh_multicast_scouting", settings.zenoh_multicast_scouting),
    )


class Bus:
    """One Zenoh session; incoming messages go to ``inbox``, to be drained by one worker."""

    def __init__(
        self, settings: Settings, inbox: queue.Queue, on_overload: Callable[[Kind], None]
    ) -> None:
        self.settings = settings
        self.keys: Keys = settings.keys
        self.inbox = inbox
        self._on_overload = on_overload
        self.session: zenoh.Session | None = None
        self._entities: list = []

    def open(self) -> None:
        self.session = zenoh.open(zenoh_config(self.settings))
        try:
            s, k = self.session, self.keys
            self._entities = [
                s.declare_subscriber(k.all_samples, self._handler(Kind.sample)),
                s.declare_subscriber(k.batch, self._handler(Kind.batch)),
                s.declare_queryable(k.all_states, self._on_query),
                s.liveliness().declare_token(k.tuner(self.settings.instance_id)),
            ]
        except BaseException:
            self.close()
            raise

    @property
    def is_open(self) -> bool:
        return self.session is not None and not self.session.is_closed()

    def _handler(self, kind: Kind) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            self._put((kind, str(sample.key_expr), sample.payload.to_bytes()))

        return on_sample

    def _on_query(self, query: zenoh.Query) -> None:
        self._put((Kind.query, str(query.key_expr), query))

    def _put(self, item: Item) -> None:
        try:
            self.inbox.put_nowait(item)
        except queue.Full:
            self._on_overload(item[0])

    def publish(self, key: str, payload: bytes) -> None:
        """Put a gains message (per loop or batched); dropped once the bus is closed (the
        store has the new gains and a gateway asks for the state when a tuner is back).

        Congestion control is BLOCK: when the link to a gateway is congested the put
        waits for room (Zenoh closes a link stuck longer than
        ``transport/link/tx/queue/congestion_control/block/wait_before_close``, 5 s by
        default) instead of silently dropping gains the tuner then assumes applied.
        """
        if self.session is None:
            log.debug("bus closed: %s not published", key)
            return
        self.session.put(
            key,
            payload,
            encoding=JSON,
            congestion_control=GAINS_CONGESTION,
            priority=GAINS_PRIORITY,
        )

    def close(self) -> None:
        """Undeclare subscribers, queryable and token, then close the session (idempotent)."""
        for entity in reversed(self._entities):
            try:
                entity.undeclare()
            except zenoh.ZError as exc:  # already gone with a closed session
                log.debug("undeclare failed: %s", exc)
        self._entities = []
        if self.session is not None and not self.session.is_closed():
            self.session.close()
        self.session = None


def reply(query: zenoh.Query, payload: bytes, *, error: bool = False) -> None:
    """Answer a state query and finalise it (a query stays open until dropped)."""
    try:
        if error:
            query.reply_err(payload, encoding=JSON)
        else:
            query.reply(query.key_expr, payload, encoding=JSON)
    finally:
        query.drop()
