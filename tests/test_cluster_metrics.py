"""A missing cluster member can be alerted on: the survivor's ``pitune_cluster_members``
drops, its ``pitune_cluster_shards_owned`` grows by the shards it took and
``pitune_cluster_takeovers_total`` counts them (real PostgreSQL, real Zenoh sessions,
in-process members; a crash is the member's renewals stopping and its bus closing)."""

from __future__ import annotations

import pytest

from service.daemon.cluster import TICKS_PER_LEASE
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from tests.tuner_support import loop_body, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(90)
LEASE_S = 5.0


def _member(tmp_path, url: str, name: str, **extra) -> Tuner:
    settings = tuner_settings(
        tmp_path, db_path=url, instance_id=name, cluster_lease_s=LEASE_S, **extra
    )
    return Tuner(settings).start()


def _metrics(member: Tuner) -> tuple[float, float, float]:
    m = member.metrics
    return (
        m.value("pitune_cluster_members"),
        m.value("pitune_cluster_shards_owned"),
        m.value("pitune_cluster_takeovers_total"),
    )


def test_a_crashed_member_shows_in_the_survivor_s_metrics(tmp_path, pg_url):
    a = _member(tmp_path, pg_url, "a")
    b = _member(tmp_path, pg_url, "b", zenoh_connect=a.settings.zenoh_listen)
    try:
        configs = [
            LoopConfig(**loop_body(f"G{g}-{i}", gateway=f"gw{g}"))
            for g in range(4)
            for i in range(10)
        ]
        a.register_many(configs)  # 4 shards, claimed by a, half handed to b by the hashing
        wait_until(
            lambda: len(a.cluster.held) == len(b.cluster.held) == 2,
            timeout=3 * LEASE_S,
            what="two shards each",
        )
        wait_until(lambda: "a" in b.bus.live_tuners(), timeout=LEASE_S, what="a's token at b")
        # b's two, released to it by a after b's first tick: counted once loaded
        wait_until(lambda: _metrics(b) == (2.0, 2.0, 2.0), timeout=LEASE_S, what="b's shards")
        assert _metrics(a) == (2.0, 2.0, 0.0)  # a claimed its shards, took none over

        a.cluster.halt()  # a crashes: no more renewals, its token gone
        a.bus.close()
        wait_until(lambda: len(b.loop_ids()) == 40, timeout=3 * LEASE_S, what="a's loops on b")
        wait_until(lambda: _metrics(b)[0] == 1.0, timeout=2 * LEASE_S / TICKS_PER_LEASE)
        assert _metrics(b) == (1.0, 4.0, 4.0)
    finally:
        b.stop()
        a.stop()
