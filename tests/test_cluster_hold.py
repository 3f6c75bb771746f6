"""The plant-wide hold in a cluster (service/daemon/holds.py): set through one member, it
holds every member's engine within one tick (each reads the store's row on its tick),
and so does a release through another member; the record is the store's, shared. Two
members in-process on a real PostgreSQL store."""

from __future__ import annotations

import time

import pytest

from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from tests.tuner_support import loop_body, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(120)
LEASE_S = 2.0
"""A tick of 0.4 s (lease_s / 5)."""


def _member(tmp_path, pg_url, name: str) -> Tuner:
    settings = tuner_settings(
        tmp_path / name, db_path=pg_url, instance_id=name, cluster_lease_s=LEASE_S
    )
    return Tuner(settings).start()


def _applied_within(member: Tuner, held: bool, since: float) -> float:
    """Seconds from ``since`` (monotonic) until ``member``'s engine applies the hold."""
    wait_until(lambda: member.engine.hold.held is held, timeout=5.0, what="the hold applied")
    return time.monotonic() - since


def test_a_hold_set_through_one_member_holds_every_member_within_a_tick(tmp_path, pg_url):
    a = _member(tmp_path, pg_url, "a")
    b = None
    try:
        b = _member(tmp_path, pg_url, "b")
        a.register_many([LoopConfig(**loop_body(f"L{i}", gateway=f"g{i}")) for i in range(8)])
        wait_until(lambda: a.cluster.shard_of and b.cluster.shard_of, 30.0, "loops on both members")
        tick = b.cluster.tick_s
        began = time.monotonic()
        held = a.set_hold("turnaround", actor="api")
        assert a.engine.hold == held  # at once on the member it went through
        assert _applied_within(b, True, began) <= tick + 0.5
        assert b.engine.hold == held
        mine = next(iter(b.cluster.shard_of))  # a loop b steps says so
        assert b.view(mine).hold.guard == "plant" and "turnaround" in b.view(mine).hold.why
        assert b.metrics.value("pitune_hold") == 1.0
        began = time.monotonic()
        b.release_hold(actor="ui:night-shift")
        assert _applied_within(a, False, began) <= tick + 0.5
        assert [(e.action, e.by) for e in a.hold_history()] == [
            ("release", "ui:night-shift"),
            ("hold", "api"),
        ]
    finally:
        if b is not None:
            b.stop()
        a.stop()
