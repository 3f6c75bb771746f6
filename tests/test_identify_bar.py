"""Issue 13's bar on a subset (slow): random FOPTD loops registered without a hint, or with
a hint 3x off and auto-rescale, through the engine; the full 60-loop measurement is
``python -m tests.identify_bar`` (numbers in docs/identification.md).

Asserted: what identification decides (every loop identified within its first 4 setpoint
moves, K and tau within 30%, no loop unstable after its 60 agent steps, every wrong hint
detected and rescaled). The
step-test MSE ratios against the true hint are measured by the full run only (the
ratios scatter both ways with the agent's own run-to-run scatter in this protocol:
docs/identification.md), so no true-hint run here; and the wrong-hint run stops at
RESCALE_TAU time constants, by which every loop has had its fifth setpoint move (moves
start at 1-2 tau and come every 3-6 tau) and been rescaled, instead of tuning on for
420 tau: the CI cost is about a third of the three full runs'."""

import pytest

from service.agent import DEFAULT_WEIGHTS
from tests.identify_bar import one, summary

pytestmark = [
    pytest.mark.slow,
    pytest.mark.timeout(3600),
    pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="no trained agent"),
]
LOOPS = 12
RESCALE_TAU = 60.0


def test_hint_free_and_wrongly_hinted_loops_are_identified_and_rescaled():
    runs = {"blind": one("blind", LOOPS, 0), "rescaled": one("rescaled", LOOPS, 0, RESCALE_TAU)}
    s = summary(runs, LOOPS, 0)
    assert s["identified"] == LOOPS
    assert s["k_within_30"] == LOOPS and s["tau_within_30"] == LOOPS
    assert s["identified_within_4_moves"] == LOOPS
    assert s["unstable"] == 0
    assert s["wrong_hint_rescaled"] == LOOPS
