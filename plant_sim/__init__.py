"""Simulated plants, the PI controller, reference tunings and the paper's metrics."""

from plant_sim.foptd import FOPTDBatch, step_response
from plant_sim.loop import LoopTrace, run_closed_loop, step_test, step_test_mse, target_filter
from plant_sim.pi import PIBatch
from plant_sim.tunings import oracle, simc, simc_improved, simc_paper, to_parallel

__all__ = [
    "FOPTDBatch",
    "LoopTrace",
    "PIBatch",
    "oracle",
    "run_closed_loop",
    "simc",
    "simc_improved",
    "simc_paper",
    "step_response",
    "step_test",
    "step_test_mse",
    "target_filter",
    "to_parallel",
]
