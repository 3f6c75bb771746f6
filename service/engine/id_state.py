"""A loop's identification state beyond the table's arrays: the events of its segment,
its latest and its in-force models, the models refuted on it, why it is where it is
(:mod:`service.engine.watch` keeps it; the runtime snapshot stores it)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from service.engine import identify
from service.units import Scaling


@dataclass(slots=True)
class Refuted:
    """A model whose tuning rang and was rolled back on the loop
    (:mod:`service.engine.refuted`)."""

    model: identify.Model
    t: float | None
    """Plant time of the rollback (None: before the loop's first sample)."""
    told: bool = False
    """A model like it came back and was declined: its audit row is written (once)."""

    def dump(self) -> dict:
        return {"model": self.model.as_dict(), "t": self.t, "told": self.told}

    @classmethod
    def load(cls, d: dict) -> Refuted:
        return cls(identify.Model.from_dict(d["model"]), d.get("t"), d.get("told", False))


NO_SAMPLES = (
    "waiting for samples: none received since registration (then for a setpoint move, or "
    "an output step in manual with op in the samples)"
)
"""Why, in the view, of a loop that never sent a sample (status ``waiting``): the default
:attr:`IdState.why` would have it wait for a setpoint move."""


@dataclass(slots=True)
class IdState:
    """A loop's identification state beyond its arrays (Python objects; one per loop, so
    slotted, and the lists empty tuples until used: ~80 bytes instead of ~260)."""

    events: Sequence[identify.EventFit] = ()
    model: identify.Model | None = None
    why: str = "waiting for a setpoint move (or an output step in manual, op in the samples)"
    in_force: identify.Model | None = None
    in_force_t: float | None = None
    scaling: Scaling | None = None
    """The scaling identification put in force (None: the config's hint, or none)."""
    starts: Sequence[int] = ()
    """Event starts (indices into the loop's recorder row; a list while recording)."""
    skipped: int = 0
    """Event closes since the last assessment (see :data:`service.engine.watch.CHECK_EVERY`)."""
    tuned_seq: int = -1
    """The seq of a first tuning from a model that holds the agent until it is verified
    (:mod:`service.engine.first_tuning`; -1: none)."""
    tuned: identify.Model | None = None
    """The model whose tuning ``tuned_seq`` put in force (what a verdict that rolls it
    back refutes; None with -1)."""
    refuted: Sequence[Refuted] = ()
    """The models refuted on the loop, oldest first (:mod:`service.engine.refuted`)."""
    hint_model: identify.Model | None = None
    """A hinted loop's latest confident model while none is in force
    (:func:`service.engine.model_check.hint_checked`)."""
    hint_base: identify.Model | None = None
    """The model a hinted loop's later confident models are compared with: its first
    confident one, then each whose tuning was put in force (``hint_checked``)."""
    paused_by: dict | None = None
    """The model that paused the loop out of the agent's envelope (while it is paused), as
    its audit row gives it (:func:`box.as_seen <service.engine.box.as_seen>`) with ``t``,
    the plant time: the loop's why names it, not a later model (None: not paused, or
    paused before session 41 kept it)."""

    @property
    def fallback(self) -> identify.Model | None:
        """The model the loop is checked on when its latest is not confident: the one in
        force, else a hinted loop's last confident one; None without either."""
        return self.in_force if self.in_force is not None else self.hint_model

    def dump(self) -> dict:
        return {
            "events": [ev.as_dict() for ev in self.events],
            "model": None if self.model is None else self.model.as_dict(),
            "why": self.why,
            "in_force": None if self.in_force is None else self.in_force.as_dict(),
            "in_force_t": self.in_force_t,
            "scaling": None if self.scaling is None else self.scaling.model_dump(),
            "tuned_seq": self.tuned_seq,
            "tuned": None if self.tuned is None else self.tuned.as_dict(),
            "refuted": [r.dump() for r in self.refuted],
            "hint_model": None if self.hint_model is None else self.hint_model.as_dict(),
            "hint_base": None if self.hint_base is None else self.hint_base.as_dict(),
            "paused_by": self.paused_by,
        }

    @classmethod
    def load(cls, d: dict) -> IdState:
        return cls(
            events=[identify.EventFit.from_dict(e) for e in d.get("events", [])],
            model=identify.Model.load(d.get("model")),
            why=d.get("why", ""),
            in_force=identify.Model.load(d.get("in_force")),
            in_force_t=d.get("in_force_t"),
            scaling=None if d.get("scaling") is None else Scaling(**d["scaling"]),
            tuned_seq=d.get("tuned_seq", -1),
            tuned=identify.Model.load(d.get("tuned")),
            refuted=[Refuted.load(r) for r in d.get("refuted", ())],
            hint_model=identify.Model.load(d.get("hint_model")),
            hint_base=identify.Model.load(d.get("hint_base")),
            paused_by=d.get("paused_by"),
        )
