"""The tuner's Zenoh side: session, sample subscribers, state queryable, liveliness token.

Zenoh callbacks run on Zenoh's threads and must never block, so they only copy the
key and payload into the tuner's :class:`Inbox`, bounded in messages and in bytes (a
full inbox drops the message and counts it, a message over
:data:`~service.wire.protocol.MAX_MESSAGE_BYTES` is refused unread and counted); the
tuner's worker thread does everything else, queries included, in the order the
callbacks queued them. Zenoh delivers the sample subscribers and the queryables on
separate threads, so a query may be queued before a sample the gateway sent just
before it: a state reply reflects the samples handled before the query was, and a
gateway that needs one of its samples reflected asks with ``after_t`` (see
docs/protocol.md, State).

While it runs, the tuner also watches the other tuners' liveliness tokens on its key
prefix (:attr:`Bus.other_tuners`): the start-up check (``service.daemon.main``) refuses
to start beside a tuner already there, and this watch notices one that comes later (or
started in the same instant), logs a warning and shows it in ``/healthz``: two tuners
on one prefix both tune the same loops. Not so for the members of a cluster sharing a
PostgreSQL store: they share the prefix by design and their leases keep each loop with
one of them.

A callback subscriber still declared when the interpreter exits hangs it (zenoh 1.10),
so :meth:`Bus.close` undeclares everything and closes the session; the tuner calls it
on every shutdown path.

Zenoh reports each transport to a router or peer opening and closing: the bus logs a
WARNING when the last one goes (the tuner is cut off: no samples in, no gains out) and an
INFO when one is back, and reports each change to ``on_link`` (``pitune_bus_connected``).
"""

from __future__ import annotations

import collections
import logging
import queue
import threading
import time
from collections.abc import Callable
from enum import IntEnum

import zenoh

from service.daemon.settings import Settings
from service.wire.protocol import MAX_MESSAGE_BYTES, Keys
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
    gateway_query = 3
    """A ``{prefix}/gateways/{gateway}/state`` query (one StateBatch reply)."""


Item = tuple[Kind, str, object]
"""(kind, key expression, payload bytes or the zenoh.Query)."""
QUERY_BYTES = 512
"""What a queued query counts against the inbox's byte bound."""


class Inbox:
    """The bounded queue between the Zenoh callbacks and the worker: at most
    ``max_items`` messages and ``max_bytes`` payload bytes (a burst of large batches
    cannot grow the process by more than that). :meth:`offer` never blocks."""

    def __init__(self, max_items: int, max_bytes: int) -> None:
        self.max_items = max_items
        self.max_bytes = max_bytes
        self.nbytes = 0
        self._items: collections.deque[tuple[Item, int]] = collections.deque()
        self._cond = threading.Condition(threading.Lock())

    def offer(self, item: Item, nbytes: int) -> bool:
        """Queue ``item`` if there is room; False (nothing queued) if not."""
        with self._cond:
            if len(self._items) >= self.max_items or self.nbytes + nbytes > self.max_bytes:
                return False
            self._items.append((item, nbytes))
            self.nbytes += nbytes
            self._cond.notify()
            return True

    def put_nowait(self, item: Item) -> None:
        """:meth:`offer` that raises ``queue.Full`` (the queue.Queue interface)."""
        if not self.offer(item, _size(item)):
            raise queue.Full

    def put(self, item: Item) -> None:
        """Queue ``item`` whatever the bounds (the stop marker)."""
        with self._cond:
            self._items.append((item, 0))
            self._cond.notify()

    def get(self, timeout: float | None = None) -> Item:
        with self._cond:
            if timeout is None:
                while not self._items:
                    self._cond.wait()
            else:
                deadline = time.monotonic() + timeout
                while not self._items:
                    left = deadline - time.monotonic()
                    if left <= 0.0:
                        raise queue.Empty
                    self._cond.wait(left)
            item, nbytes = self._items.popleft()
            self.nbytes -= nbytes
            return item

    def more(self, items: list[Item], most: int, linger_s: float, linger_bytes: int) -> None:
        """Append what is queued to ``items`` (a worker's pass, at most ``most``), and
        while every item is a batch message, wait up to ``linger_s`` (0: not at all) for
        batch payloads of ``linger_bytes`` (:mod:`service.daemon.pacing`)."""
        deadline = time.monotonic() + linger_s
        size = sum(len(p) for k, _, p in items if k is Kind.batch)
        while len(items) < most:
            try:
                items.append(self.get_nowait())
            except queue.Empty:
                left = deadline - time.monotonic()
                batches = all(item[0] is Kind.batch for item in items)
                if left <= 0.0 or size >= linger_bytes or not batches:
                    return
                try:
                    items.append(self.get(timeout=left))
                except queue.Empty:
                    return
            if items[-1][0] is Kind.batch:
                size += len(items[-1][2])

    def get_nowait(self) -> Item:
        with self._cond:
            if not self._items:
                raise queue.Empty
            item, nbytes = self._items.popleft()
            self.nbytes -= nbytes
            return item

    def qsize(self) -> int:
        return len(self._items)

    def empty(self) -> bool:
        return not self._items


def _size(item: Item) -> int:
    payload = item[2]
    return len(payload) if isinstance(payload, bytes | bytearray) else QUERY_BYTES


RX_MAX_BYTES = MAX_MESSAGE_BYTES + (1 << 20)
"""Largest message Zenoh reassembles for the tuner (its links' ``rx/max_message_size``,
whatever the config file says): the tuner refuses a message over
:data:`MAX_MESSAGE_BYTES` unread (``too_large``), but Zenoh had assembled it first; a
300 MB one cost 290 MB and three 31 MiB ones 1.7 GB (a security review, session 36).
Beyond this, Zenoh drops the message on arrival (a message up to 1 MiB over the limit
still reaches the tuner, to be counted ``too_large``)."""


def zenoh_config(settings: Settings) -> zenoh.Config:
    """Zenoh config: the JSON5 file if given, then the settings' mode and endpoints.

    Without a file, every setting applies (peer on loopback, no multicast scouting).
    With a file, only settings given explicitly (flag, environment, config) override it,
    so TLS and user/password sections of the file stay in charge.
    """
    explicit = None if settings.zenoh_config is None else settings.model_fields_set

    def given(field: str, value: object) -> object:
        return value if explicit is None or field in explicit else None

    config = session_config(
        config_file=settings.zenoh_config,
        mode=given("zenoh_mode", settings.zenoh_mode),
        listen=given("zenoh_listen", settings.zenoh_listen),
        connect=given("zenoh_connect", settings.zenoh_connect),
        multicast_scouting=given("zenoh_multicast_scouting", settings.zenoh_multicast_scouting),
    )
    config.insert_json5("transport/link/rx/max_message_size", str(RX_MAX_BYTES))
    return config


class Bus:
    """One Zenoh session; incoming messages go to ``inbox``, to be drained by one worker."""

    def __init__(
        self,
        settings: Settings,
        inbox: Inbox,
        on_overload: Callable[[Item, str], None],
        on_link: Callable[[bool], None] = lambda connected: None,
    ) -> None:
        self.settings = settings
        self.keys: Keys = settings.keys
        self.inbox = inbox
        self._on_overload = on_overload
        """Called with an item not queued and why ("overload" or "too_large")."""
        self._on_link = on_link
        """Called with :attr:`connected` whenever it changes (on Zenoh's thread)."""
        self._link: bool | None = None
        self._link_lock = threading.Lock()
        self._remote: set[str] = set()  # routers and peers with a transport open
        self._link_listener = None
        self.was_connected = False
        """The bus was connected once: not connected now means the link went (``/readyz``
        says "disconnected", not "starting")."""
        self.session: zenoh.Session | None = None
        self._entities: list = []
        self._token = None
        self._followed: dict[str, object] = {}
        """Gateway -> subscriber of its samples key (a cluster's member: its own gateways)."""
        self._follow_lock = threading.Lock()
        self.other_tuners: set[str] = set()
        self.on_member: Callable[[str, bool], None] | None = None
        """A cluster member's: called with (instance id, token there) as another member's
        liveliness token comes or goes (:meth:`Suspects.token_changed
        <service.daemon.suspects.Suspects.token_changed>`)."""
        """Liveliness tokens of other tuners on this key prefix that appeared while this
        tuner ran (those already there at start-up are the start-up check's)."""

    def open(self) -> None:
        self.session = zenoh.open(zenoh_config(self.settings))
        try:
            s, k = self.session, self.keys
            self._entities = [
                s.declare_subscriber(k.all_samples, self._handler(Kind.sample)),
                s.declare_subscriber(k.batch, self._handler(Kind.batch)),
                s.declare_queryable(k.all_states, self._query_handler(Kind.query)),
                s.declare_queryable(k.all_gateway_states, self._query_handler(Kind.gateway_query)),
            ]
            if not self.settings.postgres:  # a cluster's member follows its own gateways
                self._entities.append(
                    s.declare_subscriber(k.all_gateway_samples, self._handler(Kind.batch))
                )
            self._token = s.liveliness().declare_token(k.tuner(self.settings.instance_id))
            # no history: tokens already there are the start-up check's (a get after this);
            # members of a cluster (a PostgreSQL store) share the prefix by design
            on_tuner = self._on_member if self.settings.postgres else self._on_tuner
            self._entities.append(
                s.liveliness().declare_subscriber(k.all_tuners, on_tuner, history=False)
            )
            # history: the transports open already come first, so none is missed
            self._link_listener = s.info.declare_transport_events_listener(
                self._transport_event, history=True
            )
            self._link_changed()  # the state at start (not yet connected: "starting")
        except BaseException:
            self.close()
            raise

    @property
    def is_open(self) -> bool:
        return self.session is not None and not self.session.is_closed()

    @property
    def connected(self) -> bool:
        """Whether samples can arrive and gains can leave: the session is open and, when
        this tuner is meant to reach routers or peers (connect endpoints, client mode),
        at least one router or peer is connected. A tuner that only listens (gateways
        connect to it) is connected once its session is open."""
        session = self.session
        if session is None or session.is_closed():
            return False
        return not self._must_connect() or bool(self._remote)

    def _transport_event(self, event) -> None:
        """A transport to a router or peer opened or closed. The routers and peers are
        counted from these events: asked of the session in the close event's callback,
        they still listed the closing router (CI, a loaded machine), and the loss was
        never seen. A client (a gateway connecting to this tuner) is no route out."""
        remote = event.transport
        if remote.whatami == zenoh.WhatAmI.CLIENT:
            return
        with self._link_lock:
            if event.kind == zenoh.SampleKind.PUT:
                self._remote.add(str(remote.zid))
            else:
                self._remote.discard(str(remote.zid))
        self._link_changed()

    def _link_changed(self) -> None:
        """A transport opened or closed (or the bus opened): log and report a change of
        :attr:`connected`. Not at start-up: a tuner not yet connected is "starting"."""
        with self._link_lock:
            now = self.connected
            if now == self._link:
                return
            if now and self.was_connected:
                log.info("bus connected again (routers %s, peers %s)", *self._zids())
            elif not now and self._link is not None:
                log.warning(
                    "bus disconnected: no router or peer reachable (connect %s); no samples "
                    "arrive and no gains leave until one is back",
                    self.settings.zenoh_connect,
                )
            self.was_connected |= now
            self._link = now
            self._on_link(now)

    def _zids(self) -> tuple[list[str], list[str]]:
        try:
            info = self.session.info
            return [str(z) for z in info.routers_zid()], [str(z) for z in info.peers_zid()]
        except (zenoh.ZError, AttributeError):  # closed meanwhile
            return [], []

    def _must_connect(self) -> bool:
        if self.settings.zenoh_mode == "client" or self.settings.zenoh_connect:
            return True
        if self.settings.zenoh_config is None:
            return False
        try:
            endpoints = zenoh_config(self.settings).get_json("connect/endpoints")
        except (zenoh.ZError, ValueError):
            return False
        return endpoints not in ("[]", "null", "{}", "")

    def _on_member(self, sample: zenoh.Sample) -> None:
        """Another member's token came or went (a crashed member's goes at once)."""
        member = str(sample.key_expr).rsplit("/", 1)[-1]
        if member != self.settings.instance_id and self.on_member is not None:
            self.on_member(member, sample.kind == zenoh.SampleKind.PUT)

    def _on_tuner(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if key == self.keys.tuner(self.settings.instance_id):
            return
        if sample.kind == zenoh.SampleKind.PUT:
            self.other_tuners.add(key)
            log.warning(
                "another tuner appeared on the bus with key prefix %r: %s. Both tune the same "
                "loops: stop it, or give it its own --prefix (PITUNE_KEY_PREFIX)",
                self.settings.key_prefix,
                key,
            )
        elif key in self.other_tuners:
            self.other_tuners.discard(key)
            log.warning("the other tuner %s left the bus", key)

    def _handler(self, kind: Kind) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            payload = sample.payload
            key = str(sample.key_expr)
            if len(payload) > MAX_MESSAGE_BYTES:  # refused unread: no copy, no parse
                self._on_overload((kind, key, b""), "too_large")
                return
            data = payload.to_bytes()
            if not self.inbox.offer((kind, key, data), len(data)):
                self._on_overload((kind, key, data), "overload")

        return on_sample

    def _query_handler(self, kind: Kind) -> Callable[[zenoh.Query], None]:
        def on_query(query: zenoh.Query) -> None:
            item = (kind, str(query.key_expr), query)
            if not self.inbox.offer(item, QUERY_BYTES):
                self._on_overload(item, "overload")

        return on_query

    def follow(self, gateways: set[str]) -> None:
        """Subscribe to the samples keys of ``gateways`` (a cluster's member, for the
        gateway shards it just took): Zenoh then routes those batches to this member
        only, instead of every batch to every member."""
        with self._follow_lock:
            if self.session is None:
                return
            for gateway in sorted(gateways - set(self._followed)):
                key = self.keys.gateway_samples(gateway)
                self._followed[gateway] = self.session.declare_subscriber(
                    key, self._handler(Kind.batch)
                )

    def unfollow(self, gateways: set[str]) -> None:
        """Stop receiving the samples of ``gateways`` (shards released or lost)."""
        with self._follow_lock:
            for gateway in gateways:
                sub = self._followed.pop(gateway, None)
                if sub is not None:
                    _undeclare(sub)

    def live_tuners(self, timeout: float = 0.5) -> set[str]:
        """Instance ids of the tuners whose liveliness tokens are on the bus now (a
        process that died lost its token when its connections closed; one that is only
        slow keeps it)."""
        if self.session is None:
            return set()
        ids = set()
        for reply in self.session.liveliness().get(self.keys.all_tuners, timeout=timeout):
            if reply.ok is not None:
                ids.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        return ids

    @property
    def followed(self) -> set[str]:
        return set(self._followed)

    def stop_receiving(self) -> None:
        """Undeclare the subscribers and queryables (the session stays open to publish)."""
        self.unfollow(self.followed)
        for entity in reversed(self._entities):
            _undeclare(entity)
        self._entities = []

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
        """Undeclare subscribers, queryables and token, then close the session (idempotent)."""
        self.stop_receiving()
        if self._link_listener is not None:  # first: closing the session is no lost link
            _undeclare(self._link_listener)
            self._link_listener = None
        if self._token is not None:
            _undeclare(self._token)
            self._token = None
        if self.session is not None and not self.session.is_closed():
            self.session.close()
        self.session = None


def _undeclare(entity) -> None:
    try:
        entity.undeclare()
    except zenoh.ZError as exc:  # already gone with a closed session
        log.debug("undeclare failed: %s", exc)


def reply(query: zenoh.Query, payload: bytes, *, error: bool = False) -> None:
    """Answer a state query and finalise it (a query stays open until dropped)."""
    try:
        if error:
            query.reply_err(payload, encoding=JSON)
        else:
            query.reply(query.key_expr, payload, encoding=JSON)
    finally:
        query.drop()
