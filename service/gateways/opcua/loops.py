"""The gateway's view of each loop: the block's values as last notified, the update
waiting to be written, and the write policy's decision for it (:func:`decide`)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

from asyncua import ua

from service.gateways.base import Source, Update
from service.gateways.opcua.forms import FormError
from service.gateways.opcua.sitemap import LoopMap

REL_TOL = 1e-5
"""Read-back and comparisons of gains: float32 nodes round to ~6e-8."""
WAIT = "wait"


INTEGER_TYPES = frozenset(
    getattr(ua.VariantType, name)
    for name in ("SByte", "Byte", "Int16", "UInt16", "Int32", "UInt32", "Int64", "UInt64")
)


def close_to(a: tuple[float | None, ...] | None, b: tuple[float | None, ...] | None) -> bool:
    """Equal within REL_TOL; an unknown value (None) is equal to nothing."""
    if a is None or b is None or None in a or None in b:
        return False
    return all(math.isclose(x, y, rel_tol=REL_TOL, abs_tol=0.0) for x, y in zip(a, b, strict=True))


def node_value(value: float, vtype: Any) -> float | int | None:
    """``value`` as a node of type ``vtype`` takes it: an integer for an integer node, if
    ``value`` is integral within REL_TOL (a form conversion's rounding), else None."""
    if vtype not in INTEGER_TYPES:
        return value
    whole = round(value)
    return whole if math.isclose(value, whole, rel_tol=REL_TOL, abs_tol=0.0) else None


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
    """The block's (P, I) the update is known to be newer than: a write goes out only if
    they still hold (None: nothing known, never written). See :meth:`LoopRuntime.base`."""


@dataclass
class LoopRuntime:
    index: int
    cfg: LoopMap
    values: dict[str, Any] = field(default_factory=dict)
    types: dict[str, Any] = field(default_factory=dict)
    last_t: float | None = None
    """The source time of the loop's last sample."""
    replays: int = 0
    """PV values still to come that may re-deliver one sent before a (re)connect."""
    pending: Pending | None = None
    last_write: float = -math.inf
    settled: tuple[float, float] | None = None
    """The block's (P, I) when the gateway last finished an update (None: none since it
    started, or the gains were not known then): what the tuner's later updates follow."""

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

    def base(self, update: Update) -> tuple[float, float] | None:
        """The gains ``update`` is known to follow (rule 6). A live gains message follows
        the gains the block has as it arrives. A state reply may be older than them: it
        may be the update already written before this gateway started, with an operator's
        change since. It follows only the gains of the gateway's last finished update
        (the seq rule took the reply as newer than that update); so does a live message
        arriving while the block's gains are unknown (before the first read, bad quality)."""
        live = update.source not in (Source.state, Source.state_batch)
        gains = self.block_gains() if live else None
        return self.settled if gains is None else gains

    def finish(self) -> None:
        """The pending update is finished with: the gains in force now are the ones the
        samples report with its seq."""
        self.pending = None
        self.settled = self.block_gains()

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
    target = tuple(node_value(v, lr.types.get(n)) for v, n in zip(target, ("p", "i"), strict=True))
    if None in target:  # an integer node and a fractional value: never rounded
        return "not_integral"
    current = lr.block_gains()
    if current is None:
        return WAIT
    if lr.in_force() is None:  # e.g. a negative gain (a DCS that signs it by the action):
        return "invalid_block_gains"  # never overwritten by pitune's positive one
    if close_to(current, target):
        return "applied"
    if not close_to(current, lr.pending.base):
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
