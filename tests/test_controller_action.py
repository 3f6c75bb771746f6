"""Controller action (docs/tuner.md, Controller action): a direct-acting loop -- a
process whose PV falls as the output rises -- is registered with ``action: "direct"`` and
positive gains, and is tuned as well as a reverse-acting one; the registration's sanity
rules refuse what cannot be tuned (P-only, signed gains, a hint faster than the
sampling, gains orders of magnitude off the hint)."""

from __future__ import annotations

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from plant_sim.config import LoopSpec, Simulation, untuned_baseline
from plant_sim.trajectory import read_log
from service.agent import DEFAULT_WEIGHTS
from service.daemon.api import create_app
from service.engine import LoopConfig, TuningEngine
from service.engine.config import Registration
from service.procs import Stack
from tests.tuner_support import loop_body, tuner_settings

pytestmark = pytest.mark.timeout(180)
DIRECT = "cool1:K=-2,tau=20,theta=5"
"""A cooling loop: K = -2 PV units per output unit (more coolant, lower temperature)."""


def test_a_negative_gain_plant_is_registered_direct_with_magnitudes():
    spec = LoopSpec.parse("foptd", DIRECT)
    body = spec.registration(1.0)
    assert body["action"] == "direct" and body["scaling"]["k_hat"] == 2.0
    assert body["kp"] > 0 and body["ki"] > 0
    assert Registration(**body).action_sign == -1.0
    assert "action" not in LoopSpec.parse("foptd", "f:K=2,tau=20,theta=5").registration(1.0)


def test_the_engine_sees_a_direct_loop_as_the_reverse_loop_mirrored():
    """The same plant data, mirrored (K -> -K, PV -> -PV about the setpoint), gives the
    same gain decisions when the mirrored loop is registered direct-acting."""
    engine = TuningEngine(agent=None)
    base = {"kp": 0.05, "ki": 0.005, "sample_period_s": 1.0, "guard": {"excitation_periods": 0},
            "scaling": {"k_hat": 2.0, "tau_hat": 20.0}}  # fmt: skip
    engine.register(LoopConfig(id="rev", **base))
    engine.register(LoopConfig(id="dir", action="direct", **base))
    rng = np.random.default_rng(1)
    updates = []
    for i in range(800):
        sp, pv = float(rng.choice([-1.0, 1.0])), float(rng.normal())
        updates += engine.ingest(
            [
                {"loop_id": "rev", "t": float(i), "sp": sp, "pv": pv},
                {"loop_id": "dir", "t": float(i), "sp": -sp, "pv": -pv},
            ]  # fmt: skip
        )
    by = {lid: [(u.seq, u.kp, u.ki) for u in updates if u.loop_id == lid] for lid in ("rev", "dir")}
    assert len(by["rev"]) >= 6 and len(by["dir"]) == len(by["rev"])
    # equal up to float32 inference (the two rows sit apart in the batch)
    assert np.array(by["dir"]) == pytest.approx(np.array(by["rev"]), rel=1e-5)


def test_a_direct_loops_figures_read_as_its_setpoint_moved():
    """The engine judges a direct-acting loop on its mirrored error (rules.py); the view
    names directions and the error as the user's setpoint and PV have them: an upward
    move of a cooling loop is its upward figure, its error sp - pv (before: filed as a
    downward move, the error's sign flipped; the review's C01 against A01)."""
    from plant_sim.foptd import FOPTDBatch
    from plant_sim.pi import PIBatch
    from service.learn.verification import StillAgent

    engine = TuningEngine(StillAgent())
    base = {"kp": 0.1, "ki": 0.005, "sample_period_s": 1.0,
            "scaling": {"k_hat": 2.0, "tau_hat": 20.0}}  # fmt: skip
    engine.register(LoopConfig(id="rev", **base), wall=0.0)
    engine.register(LoopConfig(id="dir", action="direct", **base), wall=0.0)
    # the same physical loop twice: K = 2 under a reverse block, K = -2 under a direct one
    plant = FOPTDBatch(np.array([2.0, -2.0]), 20.0, 5.0, dt=1.0, n=2)
    plant.reset(np.array([40.0, 40.0]))
    pi = PIBatch(np.full(2, 0.1), np.full(2, 0.005), dt=1.0, n=2)
    pi.initialise(np.array([20.0, -20.0]))
    for i in range(400):  # one upward move, at t = 100
        sp, y = (40.0 if i < 100 else 60.0), plant.output()
        u = pi.step(np.array([1.0, -1.0]) * (sp - y))
        engine.ingest([{"loop_id": lid, "t": float(i), "sp": sp, "pv": float(y[j]),
                        "kp": 0.1, "ki": 0.005} for j, lid in enumerate(("rev", "dir"))],
                      wall=float(i))  # fmt: skip
        plant.step(u)
    rev, dir_ = (engine.performance(lid) for lid in ("rev", "dir"))
    assert rev.verification.last_good_iae is not None
    assert rev.verification.last_good_iae_down is None is dir_.verification.last_good_iae_down
    assert dir_.verification.last_good_iae == rev.verification.last_good_iae
    assert dir_.window.error_mean == rev.window.error_mean > 0.5  # still below the setpoint


@pytest.mark.parametrize(
    ("change", "says"),
    [
        ({"ki": 0}, "P-only"),
        ({"kp": -0.5}, "action 'direct'"),
        ({"scaling": {"k_hat": -1.2, "tau_hat": 30.0}}, "action 'direct'"),
        ({"scaling": {"k_hat": 1.2, "tau_hat": 0.5}, "sample_period_s": 10.0}, "sample period"),
        ({"kp": 1e11}, "off by orders of magnitude"),
        ({"ki": 1e-12}, "off by orders of magnitude"),
    ],
)  # fmt: skip
def test_a_registration_that_cannot_be_tuned_is_refused_with_the_reason(change, says):
    body = {"id": "L", "kp": 0.5, "ki": 0.01, "sample_period_s": 1.0,
            "scaling": {"k_hat": 1.2, "tau_hat": 30.0, "pv_scale": 10.0}, **change}  # fmt: skip
    with pytest.raises(ValueError, match=says):
        Registration(**body)
    if "kp" in change and change["kp"] > 0 or "sample_period_s" in change:
        LoopConfig(**body)  # a stored config is not judged again


@pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="trained agent weights absent")
def test_a_direct_acting_foptd_loop_is_tuned_through_the_daemon(tmp_path):
    """Tuner and plant simulator as processes, real Zenoh and HTTP: the cooling loop's
    tracking MSE against the target falls well below the untuned run's (same seed)."""
    duration = 3600.0
    spec = LoopSpec.parse("foptd", DIRECT)
    with Stack(tmp_path, speed=300.0) as stack:
        stack.start_tuner()
        plant = stack.start_plant("--foptd", DIRECT, "--duration", f"{duration:g}")
        assert plant.wait(120) == 0
        with httpx.Client(base_url=stack.api, timeout=5.0) as api:
            view = api.get("/loops/cool1").json()
    assert view["config"]["action"] == "direct" and view["seq"] >= 10
    tuned = read_log(stack.log_dir / "cool1.csv")
    untuned = untuned_baseline((spec,), Simulation(duration=duration))["cool1"]
    np.testing.assert_array_equal(tuned.sp, untuned.sp)
    mse_tuned, mse_untuned = tuned.tracking_mse(2), untuned.tracking_mse(2)
    assert mse_untuned >= 3 * mse_tuned, (mse_tuned, mse_untuned)
    assert tuned.kp[-1] > 3 * tuned.kp[0]  # tuned up from the paper's slow start


def test_the_api_refuses_what_cannot_be_tuned_with_a_422_and_registers_nothing(tmp_path):
    with TestClient(create_app(tuner_settings(tmp_path))) as client:
        bad = [loop_body("A", sample_period_s=10.0, scaling={"k_hat": 1.2, "tau_hat": 0.5}),
               loop_body("B", kp=1e11), loop_body("C", ki=0)]  # fmt: skip
        for body in bad:
            r = client.post("/loops", json=body)
            assert r.status_code == 422, r.text
            assert r.json()["detail"][0]["msg"].startswith("Value error, ")
        r = client.post("/loops/bulk", json=[loop_body("D"), bad[0]])
        assert r.status_code == 422 and "shorter than the sample period" in r.text
        assert client.get("/loops").json()["items"] == []
        r = client.post("/loops", json=loop_body("E", action="direct"))
        assert r.status_code == 201 and r.json()["config"]["action"] == "direct"


def test_identification_tells_a_hint_free_loop_registered_with_the_wrong_action():
    """A cooling loop registered without a hint: with action 'direct' its model is
    identified with the gain's magnitude and the loop is tuned; registered 'reverse' by
    mistake, identification finds a negative gain, says so, and the loop is not tuned."""
    spec = LoopSpec.parse("foptd", DIRECT)
    engine = TuningEngine(max_rate_hz=1e6)
    for action in ("reverse", "direct"):
        loop = spec.build(Simulation(sp_period=150.0), seed=0, t0=0.0)
        kp, ki = spec.initial_gains()
        engine.register(
            LoopConfig(id=action, kp=kp, ki=ki, sample_period_s=1.0, action=action), wall=0.0
        )
        scans = [loop.scan() for _ in range(2400)]
        engine.ingest([{"loop_id": action, "t": s.t, "sp": s.sp, "pv": s.pv, "kp": s.kp,
                        "ki": s.ki, "op": s.op} for s in scans], wall=0.0)  # fmt: skip
    # one wall time for all: the fits take seconds on a loaded machine (not stale)
    wrong, right = engine.view("reverse", wall=0.0), engine.view("direct", wall=0.0)
    assert wrong.status == "identifying" and wrong.scaling is None
    assert "wrong sign for the registered controller action" in wrong.identification.why
    assert wrong.identification.model.k == pytest.approx(-2.0, rel=0.05)
    assert right.status == "tuning" and right.identification.model.confident
    assert right.identification.model.k == pytest.approx(2.0, rel=0.05)
