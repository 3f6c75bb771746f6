"""The harness of tests/identify_limits.py: its closed loop is the bar's loop (a noise-free
record identifies the true plant), and its rule counts what the bar counts."""

import numpy as np
import pytest
from scipy.stats import binom

from service.engine import identify
from tests.identify_bar import Plants
from tests.identify_limits import closed_loop, rule


def test_a_noise_free_record_identifies_the_true_plant_from_two_moves():
    p = Plants.random(60, 0)
    i = 12  # theta/tau 0.81, 29 samples per tau: one of seed 0's tau misses with noise
    r = closed_loop(p, i, np.random.default_rng(3), moves=3, noise=0.0)
    assert len(r.moves) == 2 and r.moves[0] > 0
    # the PI law's reconstruction starts at 0 (the plant's input is y0/K): only the
    # moves show in it
    end = r.t.size
    m = identify.assess(r.t[:end], r.sp[:end], r.pv[:end], r.op[:end], r.moves).model
    assert m.k == pytest.approx(p.K[i], rel=1e-3)
    assert m.tau == pytest.approx(p.tau[i], rel=1e-2)
    # the plant rounds its dead time to whole samples
    assert abs(m.theta - p.theta[i]) <= p.h[i]


FIELDS = ("moves", "confident", "tau_rse", "k_err", "tau_err", "excess")


def _draw(*events):
    return {"events": [dict(zip(FIELDS, e, strict=True)) for e in events]}


def test_the_rule_takes_the_first_model_its_limit_accepts():
    ok = (0.0, 0.0, 1.0)  # K and tau exact
    draws = [
        _draw(
            (2, True, 0.16, 0.0, 0.4, 5.0), (3, True, 0.09, 0.0, 0.05, 1.0), (4, True, 0.05, *ok)
        ),
        _draw((2, False, 0.3, *ok), (3, True, 0.12, 0.35, 0.0, 2.0), (4, True, 0.1, *ok)),
        _draw((2, False, 0.5, *ok), (3, False, 0.4, *ok), (4, False, 0.3, *ok)),
    ]
    loose = rule(draws, 0.17)  # the first draw at 2 moves (tau +40 %), the second at 3 (K +35 %)
    assert loose["identified"] == pytest.approx(2 / 3)
    assert loose["misses"] == 1.0 and loose["miss_excess"] == [2.0, 5.0]
    assert loose["all_57_within"] == 0.0 and loose["both_lines"] == 0.0
    strict = rule(draws, 0.1)  # the first draw at 3 moves (5 %), the second at 4
    assert strict["identified"] == pytest.approx(2 / 3) and strict["misses"] == 0.0
    assert strict["at_least_57_of_60"] == pytest.approx(binom.sf(56, 60, 2 / 3))
    assert strict["both_lines"] == pytest.approx(strict["at_least_57_of_60"])
