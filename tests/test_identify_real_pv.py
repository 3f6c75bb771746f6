"""Identification on what real gateways send: a PV in coarse steps (an integer register,
an ADC's resolution) is identified, not taken for a stuck transmitter; a negative gain
fitted on an output rebuilt from the PI law is bad data, not the block's action."""

import pytest

from service.agent import untrained_agent
from service.engine import TuningEngine
from tests.test_identify import TAU, K, drive, hint_free


@pytest.mark.parametrize("quantum", [1.0, 3.0])
def test_a_pv_in_coarse_steps_is_identified(quantum):
    """Moves of 20, noise 0.05: the PV repeats itself on most samples (its share of
    unchanged samples is what screened it out as frozen before)."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free(), wall=0.0)
    drive(engine, moves=6, noise=0.05, quantum=quantum)
    view = engine.view("L", wall=1e4)
    model = view.identification.in_force
    assert view.counters.identified == 1, view.identification.why
    assert model.k == pytest.approx(K, rel=0.05) and model.tau == pytest.approx(TAU, rel=0.1)


@pytest.mark.parametrize("action", ["reverse", "direct"])
def test_a_negative_gain_from_a_rebuilt_output_does_not_blame_the_action(action):
    """The valve works between 15 and 30 where every other move asks for 35 (no op, no
    flag): the fit explains the data (R2 0.9) with a negative gain. The PV and the
    output rebuilt from it flip together for either action, so the sign cannot tell the
    block's action."""
    engine = TuningEngine(untrained_agent(0))
    engine.register(hint_free().model_copy(update={"action": action}), wall=0.0)
    drive(engine, moves=6, u_min=15.0, u_max=30.0)
    why = engine.view("L", wall=1e4).identification.why
    assert "other 'action'" not in why
    assert "an output at a limit the samples do not show" in why
