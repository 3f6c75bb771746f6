"""The gateway's view of each loop: the block's values as last notified, the update
waiting to be written, and the write policy's decision for it (:func:`decide`)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

from service.gateways.base import Update
from service.gateways.opcua.forms import FormError
from service.gateways.opcua.sitemap import LoopMap

REL_TOL = 1e-5
"""Read-back and comparisons of gains: float32 nodes round to ~6e-8."""
WAIT = "wait"


def close_to(a: tuple[float, float] | None, b: tuple[float, float] | None) -> bool:
    if a is None or b is None:
        return False
    return all(math.isclose(x, y, rel_tol=REL_TOL, abs_tol=0.0) for x, y in zip(a, b, strict=True))


def number(value: Any) -> float | None:
    """A finite float from a node's value, or None (bool, text, NaN, inf)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


@dataclass
class Pending:
    update: Update
    received: float
    """time.monotonic() when the update was taken from the bus."""
    base: tuple[float, float] | None
    """The block's (P, I) when it arrived: a write goes out only if they still hold."""


@dataclass
class LoopRuntime:
    index: int
    cfg: LoopMap
    values: dict[str, Any] = field(default_factory=dict)
    types: dict[str, Any] = field(default_factory=dict)
    last_t: float | None = None
    pending: Pending | None = None
    last_write: float = -math.inf

    @property
    def auto(self) -> bool:
        if self.cfg.mode is None:
            return True
        mode = self.values.get("mode")
        if isinstance(mode, float) and mode.is_integer():
            mode = int(mode)
        return any(mode == v and type(mode) is type(v) for v in self.cfg.auto_values)

    @property
    def enabled(self) -> bool:
        te = self.cfg.tuning_enable
        return te if isinstance(te, bool) else self.values.get("tuning_enable") is True

    @property
    def saturated(self) -> bool:
        v = self.values
        return v.get("at_high_limit") is True or v.get("at_low_limit") is True

    def block_gains(self) -> tuple[float, float] | None:
        p, i = number(self.values.get("p")), number(self.values.get("i"))
        return None if p is None or i is None else (p, i)

    def in_force(self) -> tuple[float, float] | None:
        gains = self.block_gains()
        if gains is None:
            return None
        try:
            return self.cfg.form.to_parallel(*gains)
        except FormError:
            return None


POLICY_FIELDS = ("mode", "tuning_enable", "p", "i")
"""The block's values the policy judges by: read again just before a write."""


def decide(
    lr: LoopRuntime, link_up: bool, now: float, tuner_up: bool = True
) -> str | tuple[float, float]:
    """The write policy for ``lr``'s pending update (docs/opcua.md, Writing gains):
    WAIT, a refusal reason, "applied" (nothing to write) or the (P, I) to write."""
    assert lr.pending is not None
    update = lr.pending.update
    if not link_up or not tuner_up:
        return WAIT
    if not lr.auto:
        return "manual"
    if not lr.enabled:
        return "tuning_disabled"
    try:
        target = lr.cfg.form.from_parallel(update.kp, update.ki)
    except FormError:
        return "invalid"
    if not lr.cfg.limits.allows(*target):
        return "beyond_limits"
    current = lr.block_gains()
    if current is None:
        return WAIT
    if lr.in_force() is None:  # e.g. a negative gain (a DCS that signs it by the action):
        return "invalid_block_gains"  # never overwritten by pitune's positive one
    if close_to(current, target):
        return "applied"
    if lr.pending.base is not None and not close_to(current, lr.pending.base):
        return "stale"
    if now - lr.last_write < lr.cfg.min_write_interval_s:
        return WAIT
    return target


@dataclass(frozen=True)
class Event:
    """What the gateway did (for tests and tools that wait on it instead of sleeping)."""

    kind: str
    """connected, lost, connect_failed, received, written, refused, applied_already."""
    loop_id: str | None = None
    seq: int | None = None
    detail: str = ""
    at: float = field(default_factory=time.monotonic)
    """When it happened (time.monotonic())."""
