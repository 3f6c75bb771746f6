"""An operator's request that is refused leaves nothing behind, and one that is taken stays
inside the guard in force: the engine's decisions, and the admin API over the real app
with its SQLite store (a second connection holding the database's write lock)."""

import sqlite3

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.daemon.api import create_app
from service.engine import LoopConfig, TuningEngine
from service.engine.patch import LoopPatch
from service.learn.verification import StillAgent
from tests.tuner_support import loop_body, tuner_settings, wait_until

pytestmark = pytest.mark.timeout(120)
HINT = {"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0}


class Pushing(StillAgent):
    """Always asks for kp and ki 0.2 agent units higher."""

    def act(self, obs, state, forgetting):
        return np.full((len(obs), 2), 0.2), state


def _patched(engine: TuningEngine, loop_id: str, **fields) -> None:
    engine.reconfigure(LoopPatch(**fields).apply(engine.table.configs[loop_id]))


def test_a_proposal_outside_bounds_set_since_it_was_made_is_refused_and_kept():
    engine = TuningEngine(Pushing())
    engine.register(LoopConfig(
        id="A", kp=1.0, ki=0.05, sample_period_s=1.0, mode="advisory", scaling=HINT,
        guard={"excitation_periods": 0.0},
    ), wall=0.0)  # fmt: skip
    engine.ingest([{"loop_id": "A", "t": float(t), "e": 0.1} for t in range(120)], wall=0.0)
    proposal = engine.view("A").proposal
    assert proposal is not None and proposal.kp > 1.05
    _patched(engine, "A", kp_max=(1.0 + proposal.kp) / 2)  # the operator narrows the guard
    engine.drain_changes()
    with pytest.raises(ValueError, match=r"outside the guard's bounds in force \(kp 0.*: reject"):
        engine.accept("A", proposal.seq)
    view = engine.view("A")
    assert view.kp == 1.0 and view.proposal.seq == proposal.seq
    assert engine.drain_changes() == ([], [])  # nothing published, nothing audited
    engine.reject("A", proposal.seq)  # what the refusal says to do
    assert engine.view("A").proposal is None


def test_a_refused_rollback_records_no_verdict():
    engine = TuningEngine(StillAgent())
    engine.register(
        LoopConfig(id="F", kp=1.0, ki=0.05, sample_period_s=1.0, scaling=HINT), wall=0.0
    )
    engine.ingest([{"loop_id": "F", "t": 0.0, "e": 0.0, "kp": 3.0, "ki": 0.2}], wall=0.0)
    assert engine.view("F").verification.pending  # the operator's own change, adopted
    _patched(engine, "F", mode="frozen")
    engine.drain_changes()
    before = engine.view("F").verification
    with pytest.raises(ValueError, match="a frozen loop publishes no gains"):
        engine.rollback("F")
    assert engine.drain_changes() == ([], [])
    assert engine.view("F").verification == before


@pytest.fixture
def client(tmp_path):
    with TestClient(create_app(tuner_settings(tmp_path))) as c:
        yield c


def _patches(client, loop_id: str) -> int:
    rows = client.get(f"/loops/{loop_id}/history").json()["items"]
    return sum(row["reason"] == "patched" for row in rows)


def test_patch_null_restores_a_default_bound_and_is_a_422_where_there_is_none(client):
    assert client.post("/loops", json=loop_body("L1")).status_code == 201
    default = client.get("/loops/L1").json()["config"]["guard"]["kp_max"]  # from the hint
    r = client.patch("/loops/L1", json={"kp_max": default / 2, "identify": False})
    assert r.status_code == 200 and r.json()["config"]["guard"]["kp_max"] == default / 2
    r = client.patch("/loops/L1", json={"kp_max": None, "identify": None})
    guard = r.json()["config"]["guard"]
    assert r.status_code == 200 and guard["kp_max"] == default and guard["identify"] is None
    assert _patches(client, "L1") == 2
    for body in ({"mode": None}, {"max_rel_change": None, "kp_min": 0.001}):
        r = client.patch("/loops/L1", json=body)
        assert r.status_code == 422 and "null is not a value of" in r.text, r.text
        assert next(iter(body)) in r.text
    assert _patches(client, "L1") == 2  # refused: not recorded
    assert client.get("/loops/L1").json()["config"]["guard"]["kp_min"] != 0.001


def test_a_loop_without_scaling_must_keep_identification(client):
    body = loop_body("H1", guard={"identify": False})
    del body["scaling"]
    r = client.post("/loops", json=body)
    assert r.status_code == 422 and "leave guard.identify on" in r.text, r.text
    assert client.get("/loops/H1").status_code == 404
    del body["guard"]["identify"]
    assert client.post("/loops", json=body).status_code == 201
    r = client.patch("/loops/H1", json={"identify": False})
    assert r.status_code == 422 and "leave guard.identify on" in r.text, r.text
    assert client.get("/loops/H1").json()["config"]["guard"]["identify"] is None


def test_changes_the_store_cannot_commit_are_a_503_and_change_nothing(client, tmp_path):
    assert client.post("/loops", json=loop_body("L1")).status_code == 201
    other = sqlite3.connect(tmp_path / "pitune.db", isolation_level=None)
    other.execute("BEGIN IMMEDIATE")  # the write lock: the tuner's commits time out
    try:
        calls = (
            ("post", "/loops", {"json": loop_body("L2")}),
            ("patch", "/loops/L1", {"json": {"mode": "frozen"}}),
            ("delete", "/loops/L1", {}),
        )
        for method, path, kwargs in calls:
            r = getattr(client, method)(path, **kwargs)
            assert r.status_code == 503 and "store" in r.json()["detail"], (path, r.text)
        # a reset's commit fails: held, and said so (published only if the store recovers)
        r = client.post("/loops/L1/reset")
        assert r.status_code == 503 and "held, not committed" in r.json()["detail"], r.text
    finally:
        other.execute("ROLLBACK")
        other.close()
    assert client.get("/loops/L2").status_code == 404
    assert client.get("/loops/L1").json()["mode"] == "auto"
    wait_until(lambda: client.get("/healthz").status_code == 200, what="commits again")
    assert client.patch("/loops/L1", json={"mode": "frozen"}).status_code == 200


def test_the_console_recent_samples_take_any_cursor(client):
    assert client.post("/loops", json=loop_body("L1")).status_code == 201
    huge = 10**20
    r = client.get(f"/ui/api/loops/L1/recent?n={huge}&gn={huge}")
    assert r.status_code == 200 and r.json()["recent"]["t"] == [], r.text
    assert client.get("/ui/api/loops/L1/recent?n=-1").status_code == 422


def test_an_operators_own_gains_restart_the_proposal_track():
    engine = TuningEngine(Pushing())
    engine.register(LoopConfig(
        id="A", kp=1.0, ki=0.05, sample_period_s=1.0, mode="advisory", scaling=HINT,
        guard={"excitation_periods": 0.0, "max_rel_change": 0.5},
    ), wall=0.0)  # fmt: skip
    ups = engine.ingest([{"loop_id": "A", "t": float(t), "e": 0.1} for t in range(400)], wall=0.0)
    assert ups[-1].kp > 1.5  # the track walked beyond one guard step from the gains in force
    # the operator detunes the loop in the DCS: adopted, and the walk starts again from it
    samples = [{"loop_id": "A", "t": 400.0 + t, "e": 0.1, "kp": 0.5, "ki": 0.02} for t in range(60)]
    more = engine.ingest(samples, wall=0.0)
    assert engine.view("A").kp == 0.5
    assert more and all(u.kp <= 0.5 * 1.5 + 1e-9 for u in more), [u.kp for u in more]
