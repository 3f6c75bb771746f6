"""Issue 13's bar on a subset (slow): random FOPTD loops registered without a hint, or with
a hint 3x off and auto-rescale, through the engine; the full 60-loop measurement is
``python -m tests.identify_bar`` (numbers in docs/identification.md)."""

import numpy as np
import pytest

from service.agent import DEFAULT_WEIGHTS
from tests.identify_bar import one, summary

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(3600),
    pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="no trained agent"),
]
LOOPS = 12


def test_hint_free_and_wrongly_hinted_loops_reach_the_true_hints_tuning():
    runs = {w: one(w, LOOPS, 0) for w in ("true", "blind", "rescaled")}
    s = summary(runs, LOOPS, 0)
    assert s["identified"] >= LOOPS - 1
    assert s["k_within_30"] == s["identified"] and s["tau_within_30"] >= s["identified"] - 1
    assert s["unstable"] == 0
    assert s["mse_ratio_within_1_5"] >= LOOPS - 2
    assert s["wrong_hint_rescaled"] == LOOPS
    assert np.isfinite(s["wrong_hint_ratio_worst"])
