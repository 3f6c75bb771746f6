"""PostgreSQL unreachable for longer than the lease under a cluster (every member's row
and leases run out) and back: no loop changes owner, none goes back to an older state.
Before, every member dropped its loops at its first commit (refused: the leases had run
out), and the first member to tick saw only itself live and took every lease: 182-196
adoptions of 120 loops after an 8 s outage, 98 of them back to an older snapshot.
Real PostgreSQL (a server of its own, stopped and started), real Zenoh, in-process
members."""

from __future__ import annotations

import contextlib
import time

import orjson
import psycopg
import pytest

from service.bench.pgserver import PgServer
from service.daemon.admin import UnknownLoop
from service.daemon.cluster import SAFETY_S
from service.daemon.tuner import Tuner
from service.engine.config import LoopConfig
from tests.tuner_support import loop_body, open_peer, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(150)
LEASE_S = 3.0
IDS = [f"L{i:02d}" for i in range(16)]


def _member(tmp_path, url: str, name: str, **extra) -> Tuner:
    settings = tuner_settings(
        tmp_path / name, db_path=url, instance_id=name, cluster_lease_s=LEASE_S, **extra
    )
    return Tuner(settings).start()


def _state(*members: Tuner) -> dict[str, tuple[str, int, int]]:
    """Loop id -> (owner, steps, seq) of the loops in the members' engines now."""
    state = {}
    for m in members:
        for i in m.loop_ids():
            with contextlib.suppress(UnknownLoop):  # (gone meanwhile: moved)
                view = m.view(i)
                state[i] = (m.settings.instance_id, view.counters.steps, view.seq)
    return state


def test_a_store_outage_longer_than_the_lease_moves_no_loop(tmp_path):
    server = PgServer()
    url = server.create_database()
    a = _member(tmp_path, url, "a", store_failure_exit_s=120.0)
    b = _member(tmp_path, url, "b", store_failure_exit_s=120.0,
                zenoh_connect=a.settings.zenoh_listen)  # fmt: skip
    peer = open_peer([a.settings.zenoh_listen[0], b.settings.zenoh_listen[0]])
    try:
        a.register_many([LoopConfig(**loop_body(i)) for i in IDS])
        wait_until(lambda: len(_state(a, b)) == len(IDS) and a.loop_ids() and b.loop_ids(),
                   30.0, "both members owning loops")  # fmt: skip
        keys, t = a.settings.keys, 0.0

        def fed(done) -> bool:
            """Samples of every loop until ``done()``: the loops step (their state moves past
            its last snapshot)."""
            nonlocal t
            for _ in range(5):
                samples = [{"loop_id": i, "t": t, "e": 0.1} for i in IDS]
                peer.put(keys.batch, orjson.dumps({"v": 1, "samples": samples}))
                t += 1.0
            return done()

        wait_until(lambda: fed(lambda: all(s[1] > 0 for s in _state(a, b).values())), 60.0,
                   "steps")  # fmt: skip
        moves = (a.cluster.moves, b.cluster.moves)
        before = _state(a, b)
        server.halt()
        # every row and lease runs out: the members' own clocks say when (their last
        # renewal's start plus the lease, less SAFETY_S), the database's a little later
        wait_until(lambda: not a.cluster.may_publish() and not b.cluster.may_publish(),
                   2 * LEASE_S, "the leases running out")  # fmt: skip
        # the outage's length, not a wait for something to propagate: the halted database
        # gives no signal, and its own expiry comes SAFETY_S after the members' clocks say
        time.sleep(SAFETY_S + 0.5)
        server.resume()
        back = time.monotonic()
        # samples at once: commits come before the renewals, some of them; a member that
        # took the others' leases did it at its first ticks after the outage
        wait_until(lambda: fed(lambda: time.monotonic() > back + 2 * LEASE_S
                               and all(s[2] > before[i][2] for i, s in _state(a, b).items())),
                   60.0, "every loop stepped again")  # fmt: skip
        after = _state(a, b)
        assert (a.cluster.moves, b.cluster.moves) == moves  # no shard taken
        assert {i: s[0] for i, s in after.items()} == {i: s[0] for i, s in before.items()}
        assert all(after[i][1] >= before[i][1] for i in IDS), (before, after)
        assert a.gains_fenced == b.gains_fenced == 0
    finally:
        peer.close()
        b.stop()
        a.stop()
        server.stop()


def test_a_commit_refused_for_leases_that_only_ran_out_renews_them(tmp_path, pg_url):
    """The worker's first commit after an outage, before the renewal: the leases still
    this member's with its token are renewed and the commit goes through; the loops stay."""
    a = _member(tmp_path, pg_url, "a")
    try:
        a.register_many([LoopConfig(**loop_body(i)) for i in IDS[:4]])
        a.cluster.halt()  # no renewals: as while the store was unreachable
        with psycopg.connect(pg_url, autocommit=True) as conn:
            conn.execute("UPDATE leases SET expires = clock_timestamp() - interval '1 second'")
            tokens = dict(conn.execute("SELECT shard, token FROM leases").fetchall())
        view = a.reset("L00")
        assert sorted(a.loop_ids()) == IDS[:4]
        with psycopg.connect(pg_url, autocommit=True) as conn:
            (seq,) = conn.execute("SELECT seq FROM loops WHERE id = 'L00'").fetchone()
            leases = conn.execute(
                "SELECT shard, token, owner, expires > clock_timestamp() FROM leases"
            ).fetchall()
        assert seq == view.seq == 1  # committed
        assert {(s, tokens[s], "a", True) for s in tokens} == set(leases)  # renewed as they were
        assert a.cluster.may_publish()
    finally:
        a.stop()
