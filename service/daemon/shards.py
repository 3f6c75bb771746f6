"""Units of ownership in a cluster of tuners, and which member owns which.

A loop registered with a gateway belongs to that gateway's shard (``gw:<gateway>``):
one tuner owns all of a gateway's loops, so its step batches and GainsBatch messages
stay whole. Any other loop belongs to one of :data:`BUCKETS` hash buckets of its id
(``b<n>``), small enough for an even spread over a handful of tuners and few enough
that a tuner renews all its leases in one statement.

Shards are assigned by rendezvous (highest random weight) hashing over the live
members: every member computes the same owner for a shard from the same member list,
with no coordinator, and a member joining or leaving moves only the shards it wins or
held (about 1/N of them).
"""

from __future__ import annotations

import hashlib
import zlib
from collections.abc import Iterable

BUCKETS = 64
"""Hash buckets of the loops registered without a gateway."""


GATEWAY_SHARD = "gw:"


def shard_of(loop_id: str, gateway: str | None) -> str:
    """The shard a loop belongs to (fixed for the loop's lifetime: its gateway and id)."""
    if gateway:
        return gateway_shard(gateway)
    return f"b{zlib.crc32(loop_id.encode()) % BUCKETS}"


def gateway_shard(gateway: str) -> str:
    """The shard of a gateway's loops."""
    return f"{GATEWAY_SHARD}{gateway}"


def gateways(shards: Iterable[str]) -> set[str]:
    """The gateways of the gateway shards among ``shards`` (their samples keys are what
    the member owning them subscribes to)."""
    return {s[len(GATEWAY_SHARD) :] for s in shards if s.startswith(GATEWAY_SHARD)}


def _weight(member: str, shard: str) -> int:
    digest = hashlib.blake2b(f"{member}\0{shard}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big")


def owner(shard: str, members: Iterable[str]) -> str | None:
    """The member that wins ``shard`` (None without members)."""
    return max(members, key=lambda m: _weight(m, shard), default=None)


def assign(shards: Iterable[str], members: list[str]) -> dict[str, str]:
    """Shard -> winning member, for every shard (empty without members)."""
    if not members:
        return {}
    return {shard: owner(shard, members) for shard in shards}
