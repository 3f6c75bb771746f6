"""Verify-or-rollback through the real daemon (a subprocess, SQLite, Zenoh, HTTP). Two
simulated FOPTD loops, one ``auto`` and one ``advisory``, their setpoints toggling,
started on sluggish gains; after a baseline response an operator improves both loops'
gains (verified on the next response), then cuts kp so that the IAE more than doubles
(ki left as it was: no detune, which would be kept). The daemon is SIGKILLed while those
changes are pending and restarted: the last-good gains and the pending verdicts survive,
the next response fails the changes, the auto loop is rolled back (published, reason
``rollback``) and the advisory loop gets a rollback proposal, which an operator accepts
(published as ``auto``, reason ``accepted``). The history shows each change's verdict.
"""

import signal

import numpy as np
import pytest

from plant_sim import FOPTDBatch, PIBatch
from service.learn.verification import simc, true_iae
from service.procs import TunerProcess
from tests.tuner_support import Gateway, open_peer, snapshot_of, wait_until

pytestmark = pytest.mark.timeout(180)
TOKEN = "verify-token"
K, TAU, THETA = np.array([1.0, 1.5]), np.array([10.0, 8.0]), np.array([2.0, 2.0])
RL = 5.5 * TAU  # the hint is exact: RL period = 2.75 agent units of 2 tau
TOGGLE = 220  # samples (1 s) between setpoint moves: 4 RL periods of the slower loop
IDS = ["AUTO-1", "ADV-1"]


def body(i: int, kp: float, ki: float, mode: str) -> dict:
    # the untrained agent may move the gains by 1e-9 per step: they stay put
    return {
        "id": IDS[i], "kp": kp, "ki": ki, "sample_period_s": 1.0, "mode": mode,
        "scaling": {"k_hat": float(K[i]), "tau_hat": float(TAU[i]), "pv_scale": 1.0},
        "guard": {"excitation_periods": 0.0, "max_rel_change": 1e-9},
    }  # fmt: skip


class Plant:
    """Both loops, 1 s steps; applies the daemon's auto messages as a gateway would."""

    def __init__(self, gains: np.ndarray) -> None:
        self.plant = FOPTDBatch(K, TAU, THETA, dt=1.0, max_theta=3.0)
        self.plant.reset(0.0)
        self.pi = PIBatch(gains[:, 0].copy(), gains[:, 1].copy(), dt=1.0, n=2)
        self.pi.initialise(np.zeros(2))
        self.k = 0
        self.rng = np.random.default_rng(1)

    def run(self, gw: Gateway, until: int) -> None:
        while self.k < until:
            sp = float((self.k // TOGGLE) % 2)
            pv = self.plant.output() + 0.02 * self.rng.standard_normal(2)
            kp, ki = self.pi.kp.tolist(), self.pi.ki.tolist()
            for i in range(2):
                sample = {"t": float(self.k), "sp": sp, "pv": float(pv[i])}
                gw.send(IDS[i], {**sample, "kp": kp[i], "ki": ki[i]})
            self.plant.step(self.pi.step(sp - pv))
            self.k += 1

    def set(self, i: int, kp: float, ki: float) -> None:
        kps, kis = self.pi.kp.copy(), self.pi.ki.copy()
        kps[i], kis[i] = kp, ki
        self.pi.set_gains(kps, kis)


def test_a_doubled_iae_is_rolled_back_and_sigkill_keeps_last_good_and_pending(tmp_path):
    good = np.column_stack(simc(K, TAU, THETA, THETA))
    slow, bad = good * 0.5, good * [0.25, 1.0]
    horizon = 2.0 * RL
    assert (
        true_iae(K, TAU, THETA, bad, horizon) > 2 * true_iae(K, TAU, THETA, good, horizon)
    ).all()
    d = TunerProcess(
        tmp_path / "pitune.db", "--agent-weights", "untrained", "--instance-id", "proc",
        "--snapshot-interval", "3600", log=tmp_path / "daemon.log", token=TOKEN,
        env={"PITUNE_MAX_SAMPLE_RATE_HZ": "1e6"},
    )  # fmt: skip
    plant = Plant(slow)
    try:
        proc = d.start()
        with d.http() as api:
            for i, mode in enumerate(("auto", "advisory")):
                r = api.post("/loops", json=body(i, *slow[i], mode))
                assert r.status_code == 201, r.text
        gw = Gateway(open_peer([d.zenoh]))
        try:
            wait_until(lambda: list(gw.session.liveliness().get("pitune/tuners/proc", timeout=1.0)))
            plant.run(gw, 2 * TOGGLE + 20)  # the baseline response ends at TOGGLE + 2 RL
            for i in range(2):  # an operator's improving change on both loops
                plant.set(i, *good[i])
            plant.run(gw, 4 * TOGGLE + 20)  # judged (verified) at 3 TOGGLE + 2 RL
            for i in range(2):  # and a bad one
                plant.set(i, *bad[i])
            plant.run(gw, 4 * TOGGLE + 40)
            with d.http() as api:
                wait_until(
                    lambda: all(
                        api.get(f"/loops/{i}").json()["last_sample_t"] == plant.k - 1 for i in IDS
                    ),
                    what="the samples handled",
                )
                views = [api.get(f"/loops/{i}").json() for i in IDS]
            for i, v in enumerate(views):
                assert v["kp"] == pytest.approx(bad[i, 0])  # adopted
                assert v["verification"]["pending"] is True
                assert v["verification"]["last_good_kp"] == pytest.approx(good[i, 0])
                assert v["verification"]["last_good_iae"] > 0
            snap = snapshot_of(d.db, IDS[0])[1]["verify"]  # written with the verdict
            assert snap["g_kp"] == pytest.approx(good[0, 0]) and snap["g_iae"] > 0
            assert proc.signal(signal.SIGKILL) == -signal.SIGKILL
        finally:
            gw.close()

        proc = d.start()
        with d.http() as api:
            for i, loop_id in enumerate(IDS):
                v = api.get(f"/loops/{loop_id}").json()["verification"]
                assert v["pending"] is True and v["last_good_kp"] == pytest.approx(good[i, 0])
        gw = Gateway(open_peer([d.zenoh]))
        try:
            wait_until(lambda: list(gw.session.liveliness().get("pitune/tuners/proc", timeout=1.0)))
            judged_by = 5 * TOGGLE + int(2 * RL.max()) + 2  # the next complete response
            plant.run(gw, judged_by)
            seen = {}
            while len(seen) < 2:
                m = gw.next_gains(timeout=20.0)
                if m.reason in ("rollback", "accepted"):
                    seen[m.loop_id] = m
            auto, adv = seen[IDS[0]], seen[IDS[1]]
            assert (auto.mode, auto.reason) == ("auto", "rollback")
            assert (auto.kp, auto.ki) == pytest.approx(tuple(good[0]))
            assert "why=iae" in auto.why and "verdict=rolled_back" in auto.why
            assert (adv.mode, adv.reason) == ("advisory", "rollback")
            assert (adv.kp, adv.ki) == pytest.approx(tuple(good[1]))
            with d.http() as api:
                proposal = api.get(f"/loops/{IDS[1]}").json()["proposal"]
                assert proposal["reason"] == "rollback" and proposal["seq"] == adv.seq
                assert proposal["kp_in_force"] == pytest.approx(bad[1, 0])
                stale = api.post(f"/loops/{IDS[1]}/proposals/{adv.seq + 5}/accept")
                assert stale.status_code == 409
                r = api.post(f"/loops/{IDS[1]}/proposals/{adv.seq}/accept")
                assert r.status_code == 200, r.text
                assert r.json()["kp"] == pytest.approx(good[1, 0])
                accepted = gw.next_gains(timeout=10.0)
                while accepted.reason != "accepted":
                    accepted = gw.next_gains(timeout=10.0)
                assert (accepted.mode, accepted.kp) == ("auto", pytest.approx(good[1, 0]))
                history = api.get(f"/loops/{IDS[0]}/history").json()["items"]
                adopted = [e for e in history if e["reason"] == "adopted"]  # newest first
                assert [e["verdict"] for e in adopted] == ["rolled_back", "verified"]
                assert adopted[1]["kp_new"] == pytest.approx(good[0, 0])
                perf = api.get(f"/loops/{IDS[0]}/performance").json()
                # the bad gains' response is among the recent ones (under load the
                # rolled-back gains may already have answered a newer move)
                worst = max(r["iae"] for r in [perf["last"], *perf["history"]])
                assert worst > 2 * perf["verification"]["last_good_iae"] * 0.75
                assert perf["history"] and perf["verification"]["pending"] is False
                assert api.post(f"/loops/{IDS[0]}/rollback").status_code == 409  # nothing to undo
                metrics = api.get("/metrics").text
            assert 'pitune_verdicts_total{verdict="rolled_back",why="iae"} 1.0' in metrics
            assert 'pitune_verdicts_total{verdict="rollback_proposed",why="iae"} 1.0' in metrics
        finally:
            gw.close()
        assert proc.signal(signal.SIGTERM) == 0
    finally:
        d.stop()
