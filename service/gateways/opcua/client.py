"""The OPC UA side of the gateway: one secure session, monitored items, write and read back.

:class:`OpcUaLink` is one connection's life: :meth:`~OpcUaLink.open` connects with the
map's security, reads every mapped node once and creates one subscription with a
monitored item per node (the loop's sampling interval and queue size, trigger
``StatusValueTimestamp`` so that a value repeated with a new source timestamp is still
a new sample); :meth:`~OpcUaLink.events` yields the notifications in batches;
:meth:`~OpcUaLink.write` writes values in one request and reads them back in another.
Reconnecting (a new link after a loss, with backoff) is the bridge's job
(:mod:`service.gateways.opcua.bridge`), so that it controls what happens to the writes
in flight.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from asyncua import Client, ua
from asyncua.crypto import security_policies

from service.gateways.opcua.sitemap import Security, SecurityMode, ServerMap

log = logging.getLogger("pitune.gateway.opcua")
CHUNK = 500
"""Nodes per read, write or create-monitored-items request (servers cap them)."""


class LinkLost(ConnectionError):
    """The OPC UA connection is gone (server stopped, network, session closed)."""


class RequestFailed(Exception):
    """The server refused a whole request (a service fault such as BadUserAccessDenied or
    BadTooManyOperations), or the client could not encode it: the session is fine."""

    def __init__(self, code: int, detail: str = "") -> None:
        self.code = ua.StatusCode(code)
        self.reason = self.code.name
        super().__init__(f"{self.reason} {detail}".strip())


LINK_CODES = frozenset(
    getattr(ua.StatusCodes, name)
    for name in (
        "BadSessionClosed", "BadSessionIdInvalid", "BadSessionNotActivated",
        "BadSecureChannelClosed", "BadSecureChannelIdInvalid", "BadSecureChannelTokenUnknown",
        "BadConnectionClosed", "BadConnectionRejected", "BadDisconnect", "BadNotConnected",
        "BadServerNotConnected", "BadCommunicationError", "BadNoCommunication",
        "BadTimeout", "BadRequestTimeout", "BadServerHalted", "BadShutdown",
        "BadTcpInternalError",
    )
)  # fmt: skip
"""Service faults that mean the session or its channel is gone: a reconnect is due. Any
other fault of a request is the server refusing that request (:class:`RequestFailed`):
reconnecting would only repeat it, re-reading and re-monitoring every node each time."""
NULL_TIMES = (datetime(1601, 1, 1, tzinfo=UTC), datetime(9999, 12, 31, 23, 59, 59, tzinfo=UTC))
"""OPC UA's DateTime 0 (null: no timestamp) and its maximum, as asyncua decodes them."""


def request_error(exc: Exception) -> Exception:
    """What a failed request means: :class:`LinkLost` for the transport or the session,
    :class:`RequestFailed` for a fault of that request only."""
    if isinstance(exc, TimeoutError | ConnectionError):
        return LinkLost(str(exc) or type(exc).__name__)
    if isinstance(exc, ua.UaStatusCodeError):
        if exc.code in LINK_CODES:
            return LinkLost(str(exc))
        return RequestFailed(exc.code)
    # the client's own error, e.g. a value it cannot encode: the request was never sent
    return RequestFailed(ua.StatusCodes.BadUnexpectedError, str(exc))


@dataclass(frozen=True)
class Item:
    """One monitored node: which loop and which field of it."""

    loop: int
    field: str


@dataclass(frozen=True)
class Change:
    """One value change of a monitored node."""

    item: Item
    value: Any
    t: float | None
    """Source timestamp (else server timestamp), seconds since the Unix epoch."""
    good: bool
    vtype: Any = None
    """The node's variant type (writes use the same)."""


def epoch_seconds(dv: ua.DataValue) -> float | None:
    """The source timestamp, else the server timestamp, else None (a null DateTime, or
    its maximum, is no timestamp: a server that sends 0 means it has none)."""
    for ts in (dv.SourceTimestamp, dv.ServerTimestamp):
        if ts is None:
            continue
        if ts.tzinfo is None:
            ts = ts.replace(tzinfo=UTC)
        if NULL_TIMES[0] < ts < NULL_TIMES[1]:
            return ts.timestamp()
    return None


def plain(value: Any) -> Any:
    """An OPC UA value as a plain Python value (LocalizedText and enums as their text)."""
    if isinstance(value, ua.LocalizedText):
        return value.Text
    return value


async def secure_client(server: ServerMap) -> Client:
    """A client configured per the map (not connected)."""
    client = Client(server.url, timeout=server.timeout_s, watchdog_intervall=server.watchdog_s)
    client.application_uri = server.application_uri
    client.name = client.description = "pitune OPC UA gateway"
    if server.security is Security.basic256sha256:
        mode = (
            ua.MessageSecurityMode.SignAndEncrypt
            if server.mode is SecurityMode.sign_and_encrypt
            else ua.MessageSecurityMode.Sign
        )
        await client.set_security(
            security_policies.SecurityPolicyBasic256Sha256,
            certificate=str(server.certificate),
            private_key=str(server.private_key),
            server_certificate=None
            if server.server_certificate is None
            else str(server.server_certificate),
            mode=mode,
        )
    if server.user is not None:
        client.set_user(server.user)
        client.set_password(server.password() or "")
    return client


class OpcUaLink:
    """One connected session with all mapped nodes monitored."""

    def __init__(self, server: ServerMap) -> None:
        self.server = server
        self.client: Client | None = None
        self.lost = asyncio.Event()
        self._sub = None
        self._items: dict[int, list[Item]] = {}

    async def open(
        self,
        nodes: list[tuple[Item, str]],
        *,
        sampling_ms: dict[int, float],
        queue_size: dict[int, int],
        publishing_ms: float,
        before_subscribe: Callable[[list[Change]], Awaitable[None]] | None = None,
    ) -> list[Change]:
        """Connect, read every node once (returned as changes, and given to
        ``before_subscribe`` first), then monitor them all."""
        client = await secure_client(self.server)

        async def on_lost(exc: Exception) -> None:
            log.warning("OPC UA connection lost: %r", exc)
            self.lost.set()

        client.connection_lost_callback = on_lost
        try:
            await client.connect()
        except BaseException:
            with contextlib.suppress(Exception):
                await client.disconnect()
            raise
        self.client = client
        try:
            by_node: dict[str, list[Item]] = {}
            node_of = {}
            for item, node in nodes:
                by_node.setdefault(node, []).append(item)
                node_of[item] = node
            ids = {node: ua.NodeId.from_string(node) for node in by_node}
            initial = await self.read(list(ids.values()))
            changes = []
            for items, dv in zip(by_node.values(), initial, strict=True):
                for item in items:
                    changes.append(_change(item, dv))
            if before_subscribe is not None:
                await before_subscribe(changes)
            self._sub = await client.create_subscription(publishing_ms, None, queue_maxsize=0)
            aiter(self._sub)  # iterator mode: creates the (unbounded) event queue now
            trigger = ua.DataChangeFilter(Trigger=ua.DataChangeTrigger.StatusValueTimestamp)
            requests = []
            for node, items in by_node.items():
                loop = items[0].loop
                req = self._sub._make_monitored_item_request(
                    client.get_node(ids[node]),
                    ua.AttributeIds.Value,
                    trigger,
                    queue_size[loop],
                    ua.MonitoringMode.Reporting,
                    sampling_ms[loop],
                )
                self._items[req.RequestedParameters.ClientHandle] = items
                requests.append(req)
            # a node the server refuses to monitor (e.g. BadNodeIdUnknown, a typo in the map)
            # costs its loop, not the session: its initial read is bad too, so its change
            # above says so, and the loop lacks that value (no samples, or no writes)
            results = []
            for start in range(0, len(requests), CHUNK):
                results += await self._sub.create_monitored_items(requests[start : start + CHUNK])
            for req, result in zip(requests, results, strict=True):
                if isinstance(result, ua.StatusCode):
                    for item in self._items.pop(req.RequestedParameters.ClientHandle):
                        log.error("loop %d %s: %s not monitored: %s", item.loop, item.field,
                                  node_of[item], result.name)  # fmt: skip
            return changes
        except BaseException:
            await self.close()
            raise

    async def events(self, timeout: float) -> list[Change]:
        """The changes that arrived, at least one unless ``timeout`` passes or the link is
        lost (then :class:`LinkLost`)."""
        if self.lost.is_set() or self._sub is None:
            raise LinkLost("connection lost")
        queue = self._sub._event_queue
        lost = asyncio.ensure_future(self.lost.wait())
        get = asyncio.ensure_future(queue.get())
        try:
            done, _ = await asyncio.wait(
                {lost, get}, timeout=timeout, return_when=asyncio.FIRST_COMPLETED
            )
        finally:
            lost.cancel()
            if not get.done():
                get.cancel()
        if get in done:
            events = [get.result()]
        elif self.lost.is_set():
            raise LinkLost("connection lost")
        else:
            return []
        while True:
            try:
                events.append(queue.get_nowait())
            except asyncio.QueueEmpty:
                break
        if any(ev is None for ev in events):  # the subscription was closed
            self.lost.set()
        out = []
        for ev in events:
            data = getattr(ev, "data", None)
            if data is None:
                continue
            mi = data.monitored_item
            for item in self._items.get(mi.ClientHandle, ()):
                out.append(_change(item, mi.Value))
        return out

    async def read(self, nodeids: list[ua.NodeId]) -> list[ua.DataValue]:
        if self.client is None:
            raise LinkLost("not connected")
        out: list[ua.DataValue] = []
        try:
            for start in range(0, len(nodeids), CHUNK):
                out += await self.client.uaclient.read_attributes(
                    nodeids[start : start + CHUNK], ua.AttributeIds.Value
                )
        except (TimeoutError, ConnectionError, ua.UaError) as exc:
            raise request_error(exc) from exc
        return out

    async def read_items(self, nodes: list[tuple[Item, str]]) -> list[Change]:
        """The nodes' values now, as changes (one Read request per CHUNK)."""
        dvs = await self.read([ua.NodeId.from_string(node) for _, node in nodes])
        return [_change(item, dv) for (item, _), dv in zip(nodes, dvs, strict=True)]

    async def write(
        self, writes: Iterable[tuple[str, Any, ua.VariantType]]
    ) -> tuple[list[ua.StatusCode], list[ua.DataValue]]:
        """Write (node, value, type) in one request, then read them all back in another.
        :class:`LinkLost` if the session is gone, :class:`RequestFailed` if the Write
        request failed; a failed read-back gives read-backs of its bad status."""
        if self.client is None:
            raise LinkLost("not connected")
        writes = list(writes)
        ids = [ua.NodeId.from_string(node) for node, _, _ in writes]
        dvs = [ua.DataValue(ua.Variant(value, vtype)) for _, value, vtype in writes]
        codes: list[ua.StatusCode] = []
        try:
            for start in range(0, len(ids), CHUNK):
                codes += await self.client.uaclient.write_attributes(
                    ids[start : start + CHUNK], dvs[start : start + CHUNK], ua.AttributeIds.Value
                )
        except (TimeoutError, ConnectionError, ua.UaError) as exc:
            raise request_error(exc) from exc
        try:
            return codes, await self.read(ids)
        except RequestFailed as exc:  # written, not verified
            return codes, [ua.DataValue(StatusCode=exc.code) for _ in ids]

    async def close(self) -> None:
        client, self.client = self.client, None
        self._sub = None
        if client is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(client.disconnect(), timeout=self.server.timeout_s)


def _change(item: Item, dv: ua.DataValue) -> Change:
    good = dv.StatusCode is None or dv.StatusCode.is_good()
    value = plain(dv.Value.Value) if dv.Value is not None else None
    vtype = dv.Value.VariantType if dv.Value is not None else None
    return Change(item, value, epoch_seconds(dv), good and value is not None, vtype)


def now_epoch() -> float:
    return datetime.now(UTC).timestamp()
