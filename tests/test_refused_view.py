"""A loop's view says why its samples were last refused (``refused``): the reason, the
last detail, how many in the run and since when, and how many for each reason since the
loop was registered (``refused_counts``), so a gateway's integrator sees it per loop
(docs/protocol.md, Accounting). Driven through :class:`TuningEngine` with real samples;
the same view is the REST ``GET /loops/{id}``."""

from __future__ import annotations

from service.engine import LoopConfig, TuningEngine
from service.learn.verification import StillAgent
from service.wire.protocol import RejectReason


def _config(loop_id: str) -> LoopConfig:
    return LoopConfig(
        id=loop_id, kp=1.0, ki=0.05, sample_period_s=1.0,
        scaling={"k_hat": 1.0, "tau_hat": 10.0, "pv_scale": 1.0},
    )  # fmt: skip


def _sample(t: float, **extra) -> dict:
    return {"loop_id": "L", "t": t, "sp": 1.0, "pv": 0.5, **extra}


def test_the_view_names_the_last_refusal_its_run_and_since_when():
    engine = TuningEngine(StillAgent())
    engine.register(_config("L"), wall=0.0)
    engine.ingest([_sample(float(t)) for t in range(10)], wall=100.0)
    assert engine.view("L", wall=100.0).refused is None  # nothing refused yet
    engine.ingest([_sample(5.0), _sample(3.0)], wall=101.0)  # behind the last t (9)
    engine.ingest([_sample(10.0), _sample(4.0)], wall=102.0)  # one taken, one refused
    refused = engine.view("L", wall=102.0).refused
    assert refused.reason == "out_of_order" and refused.count == 3
    assert (refused.since_wall, refused.last_wall) == (101.0, 102.0)
    assert "4" in refused.detail  # the last refused sample's t
    engine.ingest([_sample(11.0, pv=2e12)], wall=103.0)  # another reason: a new run
    refused = engine.view("L", wall=103.0).refused
    assert (refused.reason, refused.count, refused.since_wall) == ("out_of_range", 1, 103.0)
    assert engine.view("L", wall=103.0).counters.rejected == 4


def test_a_deleted_loops_refusals_do_not_pass_to_the_loop_in_its_slot():
    engine = TuningEngine(StillAgent())
    engine.register(_config("L"), wall=0.0)
    engine.ingest([_sample(1.0), _sample(0.0)], wall=1.0)
    assert engine.view("L", wall=1.0).refused.count == 1
    engine.remove("L")
    engine.register(_config("M"), wall=2.0)  # takes the freed slot
    assert engine.table.slot("M") == 0
    assert engine.view("M", wall=2.0).refused is None


def test_the_view_counts_the_refusals_by_reason_since_registration():
    """A burst over the flood limit, then other reasons: ``refused`` keeps the last run
    only (one non_finite), the counts keep them all, through a reset and a restart (the
    snapshot keeps them), not passed to the next loop in a deleted loop's slot."""
    engine = TuningEngine(StillAgent(), max_rate_hz=5.0)
    engine.register(_config("L"), wall=0.0)
    engine.ingest([_sample(float(t)) for t in range(20)], wall=0.0)  # 5 taken: 15 floods
    engine.ingest([_sample(3.0)], wall=10.0)  # behind the last t (4)
    engine.ingest([_sample(30.0, pv=float("nan"))], wall=11.0)
    view = engine.view("L", wall=11.0)
    assert (view.refused.reason, view.refused.count) == ("non_finite", 1)  # the last run
    counts = {RejectReason.flood: 15, RejectReason.out_of_order: 1, RejectReason.non_finite: 1}
    assert view.refused_counts == counts and view.counters.rejected == 17
    engine.reset("L", wall=12.0)
    ((_, hidden, runtime),) = engine.snapshot()
    engine.remove("L")
    engine.register(_config("M"), wall=13.0)  # takes the freed slot
    assert engine.view("M", wall=13.0).refused_counts == {}
    engine.restore(_config("L"), kp=1.0, ki=0.05, seq=1, hidden=hidden, runtime=runtime,
                   wall=14.0)  # fmt: skip
    engine.ingest([_sample(31.0), _sample(31.0)], wall=15.0)  # a duplicate
    assert engine.view("L", wall=15.0).refused_counts == {**counts, RejectReason.duplicate: 1}
