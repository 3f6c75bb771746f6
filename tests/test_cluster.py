"""Several tuners on one PostgreSQL store (issue 20), as real processes with a real
PostgreSQL server: a killed member's loops are stepped again by the others within
10 s, continuing their seq, every published message audited; a paused member publishes
nothing after its lease ran out and rejoins; any member answers for any loop.

Scaled down for CI (3 members, 240 loops, leases of 3 s; the pause is the issue's full
30 s). The failover at the issue's full size (3,000 loops, the default 5 s leases) is
measured by ``python -m tests.test_cluster [--loops 3000]`` (docs/deploy.md, Failover)."""

from __future__ import annotations

import os
import signal
import time

import httpx
import pytest

from service.bench.cluster import (
    GainsLog,
    Load,
    Members,
    failover_delays,
    missing_audit,
    open_session,
)
from tests.tuner_support import loop_body, wait_until

pytestmark = pytest.mark.timeout(240)
LEASE_S = 3.0
FAILOVER_BAR_S = 10.0
PAUSE_S = 30.0
"""The issue's SIGSTOP: 30 s, ten leases."""


def _bodies(n: int = 240) -> list[dict]:
    """``n`` loops, three quarters on the shared samples key, the rest on 3 gateways'."""
    # RL period 27.5 s of plant time: a step every 5.5 samples (the load sends 5 s each)
    fast = {"sample_period_s": 5.0, "scaling": {"k_hat": 1.0, "tau_hat": 5.0, "pv_scale": 1.0}}
    solo = [loop_body(f"S{i:04d}", **fast) for i in range(n * 3 // 4)]
    batched = [
        loop_body(f"G{g}-{i:03d}", gateway=f"gw{g}", **fast)
        for g in range(3)
        for i in range((n - len(solo)) // 3)
    ]
    return solo + batched


@pytest.fixture
def cluster(pg_url, tmp_path):
    members = Members(3, pg_url, tmp_path, "--agent-weights", "untrained", lease_s=LEASE_S)
    try:
        members.start()
        yield members
    finally:
        members.stop()


def _running(cluster: Members, bodies: list[dict], interval: float = 0.05):
    """The load on (a batch every ``interval`` s), every loop stepped at least once;
    (session, log, load)."""
    ids = [b["id"] for b in bodies]
    r = httpx.post(f"{cluster.procs[0].api}/loops/bulk", json=bodies, timeout=60.0)
    assert r.status_code == 201, r.text
    session = open_session(cluster.endpoints)
    log = GainsLog(session)
    # the gateways' loops on their own samples keys (revision 4), the others on the shared one
    gateways = {f"gw{g}": [i for i in ids if i.startswith(f"G{g}-")] for g in range(3)}
    load = Load(session, ids, interval=interval, dt=5.0, gateways=gateways).start()

    def balanced():  # the registering member hands the shards others win to them
        view = cluster.cluster(via=1)
        loops = [m["loops"] for m in view["members"]]
        return view["unowned_loops"] == 0 and sum(loops) == len(ids) and min(loops) > 0

    wait_until(balanced, timeout=30.0, what="all three members owning loops")
    since = time.monotonic()
    wait_until(
        lambda: {h.loop_id for h in log.snapshot() if h.at > since} >= set(ids),
        timeout=60.0,
        what="every loop stepped by its owner",
    )
    return session, log, load


def _stopped_and_checked(cluster: Members, session, log: GainsLog, load: Load) -> list:
    """Stop the load and the log; every message heard, checked: no seq at or below one
    already published for its loop, every one with its audit row in the store."""
    load.stop()
    log.close()
    session.close()
    heard = log.snapshot()
    assert log.regressions() == []
    assert missing_audit(cluster.url, heard) == []
    return heard


def _killed(cluster: Members, log: GainsLog, victim: str) -> tuple[list[str], float, float, dict]:
    """SIGKILL ``victim`` under the load; (its loops, monotonic and wall time of the
    kill, each loop's delay until another member stepped it)."""
    theirs = [i for i, who in log.owners().items() if who == victim]
    assert theirs
    # any member answers for any loop: m1 forwards to the owner of one of m0's loops
    r = httpx.get(f"{cluster.procs[1].api}/loops/{theirs[0]}", timeout=10.0)
    assert r.status_code == 200 and r.json()["config"]["id"] == theirs[0]
    killed_at, killed_wall = time.monotonic(), time.time()
    cluster.by_id(victim).proc.kill()
    wait_until(
        lambda: all(
            d is not None for d in failover_delays(log, victim, theirs, killed_at).values()
        ),
        timeout=FAILOVER_BAR_S + 5.0,
        what="the killed member's loops stepped by the others",
    )
    return theirs, killed_at, killed_wall, failover_delays(log, victim, theirs, killed_at)


def test_a_killed_member_s_loops_move_within_10_s_with_seq_continuing(cluster):
    ids = [b["id"] for b in _bodies()]
    session, log, load = _running(cluster, _bodies())
    victim = "m0"
    try:
        theirs, killed_at, killed_wall, delays = _killed(cluster, log, victim)
        worst = max(delays.values())
        assert worst < FAILOVER_BAR_S, worst
    finally:
        heard = _stopped_and_checked(cluster, session, log, load)
    assert {h.instance_id for h in heard if h.loop_id in theirs and h.at > killed_at + 1} <= {
        "m1",
        "m2",
    }

    def taken_over():  # the survivors' acquisitions since the kill, done
        adoptions = [a for i in (1, 2) for a in cluster.cluster(via=i)["adoptions"]]
        return sum(a["loops"] for a in adoptions if a["at"] >= killed_wall) >= len(theirs)

    wait_until(taken_over, timeout=FAILOVER_BAR_S, what="the takeovers' records")
    # each member wrote its loop count at its takeover, not only at its next renewal
    view = cluster.cluster(via=1)
    assert view["unowned_loops"] == 0
    assert sum(m["loops"] for m in view["members"] if m["live"]) == len(ids)


def test_a_paused_member_publishes_nothing_after_its_lease_and_rejoins(cluster):
    session, log, load = _running(cluster, _bodies())
    victim = cluster.by_id("m2").proc
    theirs = [i for i, who in log.owners().items() if who == "m2"]
    assert theirs
    try:
        os.kill(victim.pid, signal.SIGSTOP)
        stopped_at = time.monotonic()
        # while it is paused, the others take its loops over
        wait_until(
            lambda: all(
                d is not None for d in failover_delays(log, "m2", theirs, stopped_at).values()
            ),
            timeout=PAUSE_S - 1.0,
            what="the paused member's loops stepped by the others",
        )
        # the rest of the pause itself is what is tested: no signal to wait on
        time.sleep(max(0.0, stopped_at + PAUSE_S - time.monotonic()))
        os.kill(victim.pid, signal.SIGCONT)
        resumed_at = time.monotonic()
        # it rejoins: it is stepping loops again, under new leases
        wait_until(
            lambda: any(
                h.instance_id == "m2" and h.at > resumed_at + LEASE_S for h in log.snapshot()
            ),
            timeout=30.0,
            what="the resumed member stepping loops again",
        )
    finally:
        if victim.running:
            os.kill(victim.pid, signal.SIGCONT)
        heard = _stopped_and_checked(cluster, session, log, load)
    # between its lease running out and its rejoining, not one message of the old leases
    # (but a repeat of one heard before: a loop's last message, sent again when it takes
    # the loop back, under the (epoch, seq) it was committed under)
    lease_end = stopped_at + LEASE_S
    old_epochs = {h.epoch for h in heard if h.instance_id == "m2" and h.at < stopped_at}
    seen, late = set(), []
    for h in heard:
        key = (h.loop_id, h.epoch, h.seq)
        old = h.instance_id == "m2" and h.at > lease_end and h.epoch in old_epochs
        if old and key not in seen:
            late.append(h)
        seen.add(key)
    assert late == []
    metrics = httpx.get(f"{cluster.by_id('m2').api}/metrics", timeout=10.0).text
    assert "pitune_samples_foreign_total" in metrics


def main() -> None:
    """The failover at the issue's full size (not in CI: a few minutes): 3 members on a
    throwaway PostgreSQL server with the default 5 s leases, ``--loops`` loops under
    load, m0 SIGKILLed; prints each of its loops' delay until another member stepped it
    and the checks of every message heard."""
    import argparse
    import statistics
    import tempfile
    from pathlib import Path

    from service.bench.pgserver import PgServer

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--loops", type=int, default=3000)
    parser.add_argument("--interval", type=float, default=0.2, help="load's batch period, s")
    args = parser.parse_args()
    server = PgServer()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            members = Members(
                3, server.create_database(), Path(tmp), "--agent-weights", "untrained"
            )
            try:
                members.start()
                session, log, load = _running(members, _bodies(args.loops), args.interval)
                try:
                    theirs, _, _, delays = _killed(members, log, "m0")
                finally:
                    heard = _stopped_and_checked(members, session, log, load)
            finally:
                members.stop()
    finally:
        server.stop()
    d = sorted(delays.values())
    print(
        f"{args.loops} loops on 3 members, m0 SIGKILLed with {len(theirs)}: stepped again by "
        f"the others after {d[0]:.2f} / {statistics.median(d):.2f} / {d[-1]:.2f} s (first / "
        f"median / last; bar {FAILOVER_BAR_S:g} s); {len(heard)} messages heard, 0 seq "
        "regressions, 0 without their audit row"
    )


if __name__ == "__main__":
    main()
