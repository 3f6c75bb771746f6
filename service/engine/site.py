"""What a site chooses for the loops that do not: the tuner's defaults for the guard
settings a registration may leave unset (null)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from service.engine.config import Guard, LoopConfig


@dataclass(frozen=True)
class SiteDefaults:
    """What a loop whose registration leaves ``guard.identify`` or ``guard.auto_rescale``
    unset (null) gets: the tuner's settings (``PITUNE_IDENTIFY_HINTED_LOOPS``,
    ``PITUNE_AUTO_RESCALE``), so that a site turns hint checks on for all its loops at
    once; a loop's own setting wins. Resolved when the config is applied, not stored:
    loops that did not choose follow the site's setting after a restart."""

    identify_hinted: bool = True
    """Identify loops registered with a hint too (their hints checked; issue 13: a hint
    is checked, not trusted). On by default since session 16: the robustness suite meets
    13 of 18 conditions with it instead of 11 and its long run wanders no more
    (docs/tuner.md, Robustness measures 1)."""
    auto_rescale: bool = False
    """Rescale a loop whose identified model disagrees with its hint."""
    fit_share: float | None = None
    """Share of one core identification's fits may take (``PITUNE_IDENTIFY_CPU_SHARE``;
    None: no limit, each assessment when due: :mod:`service.engine.fit_budget`)."""

    def identifies(self, config: LoopConfig) -> bool:
        own = config.guard.identify
        if own is not None:
            return own
        return config.scaling is None or self.identify_hinted

    def rescales(self, guard: Guard) -> bool:
        return self.auto_rescale if guard.auto_rescale is None else guard.auto_rescale
