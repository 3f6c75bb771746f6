"""A loop's history does not contradict itself: the demo's two-tank loop (+-1 cm noise,
seed 0) through the engine with the shipped agent, its audit rows in a real SQLite store,
read back as ``GET /loops/{id}/history`` reads them (the store's page, then
:func:`service.daemon.verdicts.annotate`); resets that change no gains, through the real
FastAPI app."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from plant_sim.config import LoopSpec, Simulation, build_loops
from service.agent import DEFAULT_WEIGHTS, load_agent
from service.daemon.api import create_app
from service.daemon.store import Store
from service.daemon.verdicts import annotate
from service.engine import LoopConfig, TuningEngine
from tests.tuner_support import loop_body, tuner_settings

pytestmark = pytest.mark.timeout(120)
SHIPPED = pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="trained agent weights absent")
LOOP = LoopSpec("two_tank", "tank1")


def tank_history(path) -> list:
    """An hour of the tank tuned in auto, its history newest first with verdicts."""
    sim = Simulation(duration=3600.0, noise=1.0, seed=0)
    (loop,) = build_loops((LOOP,), sim, {})
    engine = TuningEngine(load_agent())
    engine.register(LoopConfig(**LOOP.registration(sim.scan)), wall=0.0)
    store = Store(path)
    try:
        store.insert_loops([engine.table.configs[LOOP.loop_id]], engine.drain_changes()[1], [0])
        for k in range(3600):
            s = loop.scan()
            sample = {"loop_id": LOOP.loop_id, "t": s.t, "sp": s.sp, "pv": s.pv, "kp": s.kp,
                      "ki": s.ki}  # fmt: skip
            for update in engine.ingest([sample], wall=float(k)):
                loop.apply_gains(update.kp, update.ki)  # auto: each one applied
            gains, audit = engine.drain_changes()
            store.record_gains([(*g, 1) for g in gains], audit)
        _, items = store.history(LOOP.loop_id, 0, 1000)
    finally:
        store.close()
    annotate(items, int(engine.table.v_seq[engine.table.slot(LOOP.loop_id)]))
    return items


@SHIPPED
def test_a_judged_step_says_no_pending_verdict_and_a_held_step_gets_none(tmp_path):
    """The agent step's row said ``verdict=pending`` for good, beside the verdict the
    history gives it (13 of the 13 verified steps of this run); a step the model check
    held (``verdict=none``, gains unchanged) showed the verdict of the change before it
    (4 of 4)."""
    steps = [e for e in tank_history(tmp_path / "pitune.db") if e.reason == "agent"]
    assert [e.verdict for e in steps if "verdict=pending" in e.detail.split()] == []
    held = [e for e in steps if "guard=model" in e.detail.split()]
    assert held and [e.verdict for e in held] == [None] * len(held)
    assert all((e.kp_old, e.ki_old) == (e.kp_new, e.ki_new) for e in held)
    assert len([e for e in steps if e.verdict == "verified"]) >= 10
    # the newest step is still to be judged: the history says so, its row does not
    (newest,) = [e for e in steps if e.verdict == "pending"]
    assert (
        newest.detail.startswith("reason=agent basis=hint ") and "guard=none iae=" in newest.detail
    )


def test_a_reset_outside_auto_gets_no_verdict(tmp_path):
    """A reset of a ``frozen`` or ``shadow`` loop restarts the agent's state only: no
    gains published, the seq that of the change before it, whose verdict it showed
    (``pending`` here, the auto reset's: a frozen loop's reset is never judged). An
    ``advisory`` loop's is a proposal (session 41: it showed ``rollback_proposed``, the
    verdict of the change before it, and the gains had not moved)."""
    with TestClient(create_app(tuner_settings(tmp_path))) as client:
        assert client.post("/loops", json=loop_body("L1")).status_code == 201
        assert client.post("/loops/L1/reset").json()["seq"] == 1  # auto: published
        assert client.patch("/loops/L1", json={"mode": "advisory"}).status_code == 200
        view = client.post("/loops/L1/reset").json()
        assert view["seq"] == 2 and view["proposal"]["reason"] == "reset"
        for mode in ("frozen", "shadow"):
            assert client.patch("/loops/L1", json={"mode": mode}).status_code == 200
            assert client.post("/loops/L1/reset").json()["seq"] == 2
        assert client.get("/loops/L1").json()["verification"]["judged_seq"] == 0
        items = client.get("/loops/L1/history").json()["items"]
    resets = [(e["mode"], e["seq"], e["verdict"]) for e in items if e["reason"] == "reset"]
    assert resets == [
        ("shadow", 2, None), ("frozen", 2, None), ("advisory", 2, None), ("auto", 1, "pending"),
    ]  # fmt: skip
