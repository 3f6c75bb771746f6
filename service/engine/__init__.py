"""The bus-free tuning engine: samples in, gain decisions out (see
:mod:`service.engine.engine`)."""

from service.engine.config import Guard, LoopConfig, LoopView
from service.engine.engine import TuningEngine
from service.engine.patch import LoopPatch
from service.engine.site import SiteDefaults
from service.engine.updates import GainUpdate, StepResult
from service.wire.decode import Rejection

__all__ = [
    "GainUpdate",
    "Guard",
    "LoopConfig",
    "LoopPatch",
    "LoopView",
    "Rejection",
    "SiteDefaults",
    "StepResult",
    "TuningEngine",
]
