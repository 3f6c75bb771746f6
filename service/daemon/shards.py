"""Units of ownership in a cluster of tuners, and which member owns which.

A loop registered with a gateway belongs to that gateway's shard (``gw:<gateway>``):
one tuner owns all of a gateway's loops, so its step batches and GainsBatch messages
stay whole. Any other loop belongs to one of :data:`BUCKETS` hash buckets of its id
(``b<n>``), small enough for an even spread over a handful of tuners and few enough
that a tuner renews all its leases in one statement.

Shards are assigned by rendezvous (highest random weight) hashing over the live
members, with bounded loads (no member above its share of the shards, see
:func:`assign`): every member computes the same owner for a shard from the same member
and shard lists, with no coordinator.
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
    return {g for s in shards if (g := shard_gateway(s)) is not None}


def shard_gateway(shard: str) -> str | None:
    """The gateway whose shard ``shard`` is (None: a bucket of loops without one)."""
    return shard[len(GATEWAY_SHARD) :] if shard.startswith(GATEWAY_SHARD) else None


def _weight(member: str, shard: str) -> int:
    digest = hashlib.blake2b(f"{member}\0{shard}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big")


def assign(shards: Iterable[str], members: list[str]) -> dict[str, str]:
    """Shard -> member, for every shard (empty without members): rendezvous hashing with
    bounded loads. Each shard, in name order, goes to the highest-weighted member still
    under ``ceil(shards / members)``: plain rendezvous hashing gives 3 and 5 of 8
    gateways to 2 members as often as not, and a member past its share of a cluster
    sized to its members' capacity falls behind. Every member computes the same
    assignment from the same lists; a member joining or leaving moves somewhat more
    than the 1/N of plain rendezvous hashing (8 of 16 shards from 2 members to 3)."""
    if not members:
        return {}
    shards = sorted(set(shards))
    cap = -(-len(shards) // len(members))
    load = dict.fromkeys(members, 0)
    out = {}
    for shard in shards:
        ranked = sorted(members, key=lambda m: _weight(m, shard), reverse=True)
        out[shard] = next(m for m in ranked if load[m] < cap)
        load[out[shard]] += 1
    return out
