"""What the engine decides: gain updates, columnar (:class:`StepResult`) or one by one
(:class:`GainUpdate`), and the gains messages the daemon publishes for them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.wire.protocol import SCHEMA_VERSION, Mode, UpdateReason

MODE_VALUES = [m.value for m in Mode]
"""Mode names by their codes in the engine's arrays (the order of :class:`Mode`)."""
REASON_CODE = {
    UpdateReason.agent: 0, UpdateReason.reset: 1, UpdateReason.rollback: 2,
    UpdateReason.accepted: 3, UpdateReason.model: 4,
}  # fmt: skip
"""Update reasons' codes in the engine's arrays (a proposal's, ``adv_why``, which runtime
snapshots store): fixed, so that a reason added to :class:`UpdateReason`, or a reordering,
moves no stored code (a new reason takes the next free one). 0-4 are the positions in
:class:`UpdateReason` the snapshots of session 40 stored."""
REASONS = {code: reason for reason, code in REASON_CODE.items()}
"""Update reasons by their codes (:data:`REASON_CODE`)."""


@dataclass(frozen=True)
class GainUpdate:
    """New gains for one loop, engineering units (kp; ki per second)."""

    loop_id: str
    seq: int
    t: float
    """Plant time (s) of the sample that made the loop due (reset: its last sample, or 0)."""
    kp: float
    ki: float
    dkp: float
    dki: float
    mode: str
    """``auto`` (to be applied) or ``advisory`` (a proposal)."""
    reason: str
    """``agent`` (an RL step after the safety guard), ``reset``, ``rollback`` or
    ``accepted`` (an advisory proposal an operator accepted)."""
    why: str = ""
    """Short machine-readable explanation, ``key=value`` pairs (docs/tuner.md, Reasons)."""


@dataclass
class StepResult:
    """One batched decision (an RL step of several loops, or a reset); arrays are aligned
    with ``loop_ids``."""

    loop_ids: list[str]
    t: np.ndarray
    seq: np.ndarray
    mode: np.ndarray
    """Mode codes (see :data:`MODE_VALUES`)."""
    old: np.ndarray
    """(n, 2) gains before the step."""
    proposed: np.ndarray
    """(n, 2) gains the agent proposed."""
    new: np.ndarray
    """(n, 2) gains after the safety guard (published)."""
    gateways: list[str | None]
    """The gateway each loop's gains go out batched to (None: one message per loop)."""
    reason: UpdateReason = UpdateReason.agent
    inference_s: float = 0.0
    """Seconds the agent's batched step took (0 for a reset)."""
    why: list[str] | None = None
    """Per loop, the short machine-readable reason (see :class:`GainUpdate`)."""

    def __len__(self) -> int:
        return len(self.loop_ids)

    def messages(self, instance_id: str) -> list[dict]:
        """:class:`~service.wire.protocol.GainsMessage` JSON objects, built directly
        (validating a model per loop would cost more than the whole step)."""
        new, delta = self.new, self.new - self.old
        reason = self.reason.value
        modes = [MODE_VALUES[c] for c in self.mode.tolist()]
        whys = self.why if self.why is not None else [f"reason={reason}"] * len(self)
        return [
            {
                "v": SCHEMA_VERSION, "loop_id": loop_id, "seq": seq, "t": t, "dkp": dkp,
                "dki": dki, "kp": kp, "ki": ki, "mode": mode, "reason": reason,
                "instance_id": instance_id, "why": why,
            }
            for loop_id, seq, t, dkp, dki, kp, ki, mode, why in zip(
                self.loop_ids, self.seq.tolist(), self.t.tolist(), delta[:, 0].tolist(),
                delta[:, 1].tolist(), new[:, 0].tolist(), new[:, 1].tolist(), modes, whys,
                strict=True,
            )
        ]  # fmt: skip

    def without(self, rows: np.ndarray) -> StepResult:
        """The same decision without the given rows (shadow loops: nothing published)."""
        keep = np.ones(len(self), bool)
        keep[rows] = False
        idx = np.flatnonzero(keep).tolist()
        return StepResult(
            [self.loop_ids[i] for i in idx], self.t[keep], self.seq[keep], self.mode[keep],
            self.old[keep], self.proposed[keep], self.new[keep],
            [self.gateways[i] for i in idx], self.reason, self.inference_s,
            None if self.why is None else [self.why[i] for i in idx],
        )  # fmt: skip

    def updates(self) -> list[GainUpdate]:
        """The same decisions one by one."""
        return [
            GainUpdate(**{k: m[k] for k in GainUpdate.__dataclass_fields__})
            for m in self.messages("")
        ]


def published(tb, slots: np.ndarray, result: StepResult) -> StepResult:
    """``result``, the decision of the loops at ``slots`` (aligned, distinct) to publish,
    counted in their ``counters.updates``: the one place it grows, so it counts every
    gains message published (agent steps, model tunings, rollbacks, accepted proposals,
    resets) and nothing held or shadow."""
    tb.n_updates[slots] += 1
    return result
