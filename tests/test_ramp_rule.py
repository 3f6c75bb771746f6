"""The setpoint-ramp rule (service.units.ramp_rule): which setpoint changes continue a
ramp, the same over blocks of any length (training's RL periods) as sample by sample (the
engine)."""

from __future__ import annotations

import numpy as np
import pytest

from service.units import RAMP_GAP, RAMP_LONG, ramp_gated, ramp_rule


def _per_sample(sp: np.ndarray) -> list[bool]:
    last, way, since = np.array([np.nan]), np.array([np.nan]), np.array([0.0])
    out = []
    for x in sp:
        r = ramp_rule(np.array([[x]]), last, way, since)
        last, way, since = r.last, r.way, r.since
        out.append(bool(r.continues[0, 0]))
    return out


@pytest.mark.parametrize(
    ("sp", "continues"),
    [
        # a DCS ramp, one change a scan: every change after the first continues it
        ([0, 1, 2, 3, 3, 3], [False, False, True, True, False, False]),
        # a gateway polling 4x per scan of the ramp: changes RAMP_GAP samples apart
        ([0, 1, 1, 1, 1, 2, 2, 2, 2, 3], [False] * 5 + [True] + [False] * 3 + [True]),
        # an operator's steps RAMP_GAP + 1 samples apart: each a step
        ([0, 1, 1, 1, 1, 1, 2], [False] * 7),
        # a reversal starts a new ramp; samples without a setpoint change nothing
        ([0, 1, 2, 1, np.nan, 0, -1], [False, False, True, False, False, True, True]),
    ],
)
def test_which_changes_continue_a_ramp(sp, continues):
    assert RAMP_GAP == 4
    assert _per_sample(np.array(sp, float)) == continues


def test_blocks_of_any_length_give_what_samples_one_at_a_time_give():
    rng = np.random.default_rng(1)
    for _ in range(200):
        steps = rng.choice([0.0, 0.0, 0.0, 1.0, -1.0, 0.5], size=(3, 60))
        sp = np.cumsum(steps * (rng.random((3, 60)) < 0.6), axis=1)
        sp[rng.random((3, 60)) < 0.1] = np.nan
        m = int(rng.integers(1, 40))
        last, way, since = np.full(3, np.nan), np.full(3, np.nan), np.zeros(3)
        blocks = []
        for a in range(0, 60, m):
            r = ramp_rule(sp[:, a : a + m], last, way, since)
            last, way, since = r.last, r.way, r.since
            blocks.append(r.continues)
        got = np.concatenate(blocks, axis=1)
        assert [list(row) for row in got] == [_per_sample(row) for row in sp]


def test_an_rl_period_is_skipped_while_a_ramp_runs_and_after_a_long_one_only():
    period, since = 100.0, np.array([0.0, 10.0, 10.0, 10.0, 0.0])
    # running (changed a sample ago), long and ended, short and ended, long and ended a
    # period ago, and a step (a first change) after a ramp
    ramp_t = np.array([990.0, 950.0, 950.0, 890.0, 950.0])
    ramp_from = np.array([980.0, 950.0 - RAMP_LONG * period, 900.0, 700.0, 999.0])
    assert list(ramp_gated(1000.0, period, ramp_t, ramp_from, since)) == [
        True, True, False, False, False,
    ]  # fmt: skip
    # no ramp yet
    assert not ramp_gated(1000.0, period, -np.inf, -np.inf, 0.0)
