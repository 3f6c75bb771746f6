"""Identification's recorder over long segments (service.engine.watch): a full buffer
merges rows, but never the rows right after a setpoint move, so a fast loop whose
setpoint is held for many time constants is identified from the shape of each response,
as it is on a short segment."""

from __future__ import annotations

import numpy as np
import pytest

from service.agent import load_agent
from service.engine import LoopConfig, TuningEngine, identify, watch
from service.engine.recorder import CAP
from tests.test_identify import drive, gains

pytestmark = pytest.mark.timeout(120)

K, TAU, THETA, H = 2.0, 15.0, 1.5, 1.0
"""A fast loop sampled every second: 15 samples per time constant."""


def test_a_long_segment_keeps_each_moves_response_at_the_sample_period(monkeypatch):
    """Moves held 60 time constants (900 samples): six events hold 5,400 samples, ten
    times the buffer. Rows that each averaged 16-32 samples, the moves' too (the buffer
    used to halve the resolution of every row), gave confident models with tau 6-9 s
    and theta 5-6 s for this plant (the long robustness run, docs/identification.md)."""
    seen: list[tuple] = []
    real = identify.assess

    def spy(t, sp, pv, op, starts, start=None, last=1, *rest):
        out = real(t, sp, pv, op, starts, start, last, *rest)
        seen.append((np.array(t), list(starts), last, out))
        return out

    monkeypatch.setattr(identify, "assess", spy)
    kp, ki = gains(K, TAU, THETA)
    engine = TuningEngine(load_agent(None))  # identified, then tuned: still checked
    engine.register(LoopConfig(id="L", kp=kp, ki=ki, sample_period_s=H), wall=0.0)
    drive(engine, k=K, tau=TAU, theta=THETA, h=H, moves=12, every=60.0)
    late = [(t, starts, out) for t, starts, _, out in seen if len(starts) >= 5]
    assert late, "no assessment of a segment holding five events"
    for t, starts, _ in late:
        assert t.size < CAP and t[-1] - t[0] > 4_000.0  # merged: 4,000+ samples in < 512 rows
        for a in starts:  # each move's first rows: one sample each
            assert np.allclose(np.diff(t[a : a + watch.HEAD_ROWS + 1]), H)
        assert np.diff(t).max() >= 8 * H  # the quiet rows between were merged
    models = [out.model for *_, out in late if out.model is not None and out.model.confident]
    assert len(models) >= 2
    for m in models:
        assert abs(m.k / K - 1.0) < 0.05
        assert abs(m.tau / TAU - 1.0) < 0.15, (m.tau, m.theta)
        assert abs(m.theta - THETA) < 2.0 * H, (m.tau, m.theta)
