"""The plant-wide hold in the daemon (what it holds: :mod:`service.engine.plant_hold`).

It is a row of the store's ``meta`` table (:data:`KEY`), SQLite's or PostgreSQL's, so it
survives a restart (applied at start-up, before the bus opens) and reaches every member
of a cluster: the member it is set through commits and applies it at once, the others
read the row at their next tick (:meth:`PlantHolds.sync_hold`; a tick is ``lease_s / 5``).

Its record: each hold, change of reason and release is an event of the row
:data:`LOG_KEY` beside it (the last :data:`LOG_KEPT`, and the last hold's own however many
changes of its reason followed: ``GET /hold/history``), written in the same commit,
and a log line (WARNING for a hold, INFO for the rest). Not audit
rows: those are per loop, and a row for each of 10,000 loops at every hold would make a
hold cost a bulk write and bury each loop's own history; a loop's view says it is held
while it is (``hold``, guard ``plant``).
"""

from __future__ import annotations

import logging
from typing import Literal

import orjson
from pydantic import BaseModel, Field, TypeAdapter

from service.engine.plant_hold import RELEASED, PlantHold, after_put, utc

log = logging.getLogger("pitune.tuner")
KEY = "hold"
LOG_KEY = "hold_log"
LOG_KEPT = 100
"""Events kept in :data:`LOG_KEY`: each 0.08 KB with a short reason, at most 0.91 KB (200
four-byte characters, a 40-character console name), the row at most 91 KB."""


class HoldEvent(BaseModel):
    """A hold, a change of its reason, or a release (``GET /hold/history``)."""

    action: Literal["hold", "reason", "release"]
    wall_time: float = Field(description="Unix time of the change.")
    by: str = Field(description="Who made it ('api', 'ui:<name>').")
    reason: str | None = Field(description="The hold's reason (of a release: its last).")


_EVENTS = TypeAdapter(list[HoldEvent])


def _hold(value: str | None) -> PlantHold:
    return RELEASED if value is None else PlantHold.model_validate_json(value)


class PlantHolds:
    """The hold's operations, a part of :class:`~service.daemon.admin.LoopAdmin` (the
    tuner's store, engine, clock and metrics)."""

    @property
    def hold(self) -> PlantHold:
        """The hold this tuner applies (the console and ``GET /hold`` read it)."""
        return self.engine.hold

    def set_hold(self, reason: str, actor: str = "api") -> PlantHold:
        """Hold the plant (``reason`` a valid :data:`HoldReason <service.engine.
        plant_hold.HoldReason>`); already held: the reason replaced. StoreUnavailable
        (503) while commits fail."""
        return self._change_hold(lambda hold, wall: after_put(hold, reason, actor, wall), actor)

    def release_hold(self, actor: str = "api") -> PlantHold:
        """Release the plant (not held: nothing changes). StoreUnavailable while commits
        fail."""
        return self._change_hold(lambda hold, wall: RELEASED, actor)

    def hold_history(self) -> list[HoldEvent]:
        """The recorded events, newest first."""
        value = self.store.meta(LOG_KEY)
        return [] if value is None else _EVENTS.validate_json(value)

    def _change_hold(self, change, actor: str) -> PlantHold:
        """``change(hold, wall)`` applied to the stored hold (a cluster's: the latest,
        locked), committed with its event, then put in force, under the table's lock (a
        member's tick reading the row meanwhile applies it under the same lock)."""
        wall = self.clock.wall()
        seen: list[PlantHold] = []

        def rows(value_of) -> dict[str, str]:
            old = _hold(value_of(KEY))
            new = change(old, wall)
            seen[:] = [old, new]
            if new == old:
                return {}
            action = "release" if not new.held else "reason" if old.held else "hold"
            event = HoldEvent(
                action=action, wall_time=wall, by=actor, reason=new.reason or old.reason
            )
            logged = value_of(LOG_KEY)
            events = _kept([event.model_dump(), *orjson.loads(logged or "[]")])
            return {KEY: new.model_dump_json(), LOG_KEY: orjson.dumps(events).decode()}

        with self.handoff.hold():
            with self._committing():
                self.store.change_meta(KEY, RELEASED.model_dump_json(), rows)
            old, new = seen
            self._apply_hold(new)
        _announce(old, new, actor)
        return new

    def sync_hold(self) -> None:
        """Apply the hold the store has: at start-up, and at each tick of a cluster member
        (set or released through another member). Read outside the table's lock, and
        again under it only when it differs from the one applied."""
        if _hold(self.store.meta(KEY)) == self.engine.hold:
            return
        with self.handoff.hold():
            old, new = self.engine.hold, _hold(self.store.meta(KEY))
            self._apply_hold(new)
        if new != old:
            _announce(old, new, None)

    def _apply_hold(self, hold: PlantHold) -> None:
        self.engine.set_hold(hold)
        self.metrics.hold.set(1.0 if hold.held else 0.0)


def _kept(events: list[dict]) -> list[dict]:
    """Of the events, newest first, the last :data:`LOG_KEPT`, the last hold's own (the
    hold in force's, or the one last released) kept last: who held the plant and when
    stay on record however many changes of its reason follow (150 pushed it out)."""
    if len(events) <= LOG_KEPT:
        return events
    start = next((i for i, e in enumerate(events) if e["action"] == "hold"), 0)
    if start < LOG_KEPT:
        return events[:LOG_KEPT]
    return [*events[: LOG_KEPT - 1], events[start]]


def _announce(old: PlantHold, new: PlantHold, actor: str | None) -> None:
    """The log line of a change applied, made by ``actor`` (None: read from the store, set
    before this start or through another member of the cluster)."""
    read = "" if actor is not None else " (read from the store)"
    if new.held and not old.held:
        log.warning(
            "PLANT-WIDE HOLD set by %s at %s%s: %s. The tuner changes no loop's gains of "
            "its own until it is released (DELETE /hold)",
            new.by, utc(new.since or 0.0), read, new.reason,
        )  # fmt: skip
    elif new.held:
        log.info("plant-wide hold: reason changed by %s%s: %s", actor or "another member",
                 read, new.reason)  # fmt: skip
    elif old.held:
        log.info(
            "plant-wide hold released by %s%s; it was set by %s at %s: %s",
            actor or "another member", read, old.by, utc(old.since or 0.0), old.reason,
        )  # fmt: skip
