"""The plant-wide hold's REST calls (docs/tuner.md, Plant-wide hold): ``GET /hold`` the
hold in force, ``PUT /hold`` holds the plant, ``DELETE /hold`` releases it (both with the
admin token, both idempotent, both answering the new state), ``GET /hold/history`` the
holds and releases recorded. A path of its own beside ``/loops`` (one loop each) and
``/cluster``: the hold is the tuner's (every member's, in a cluster), no loop's."""

from __future__ import annotations

from fastapi import APIRouter, Request

from service.daemon.deps import TunerDep, actor_of, admin_event, mutating
from service.daemon.holds import HoldEvent
from service.engine.plant_hold import HoldRequest, PlantHold

router = APIRouter(prefix="/hold", tags=["hold"])


@router.get("")
def get_hold(tuner: TunerDep) -> PlantHold:
    """The plant-wide hold this tuner applies (``held`` false: none); in a cluster each
    member applies a change made through another within one tick."""
    return tuner.hold


@router.put("", dependencies=mutating, responses={422: {}, 503: {}})
def put_hold(body: HoldRequest, tuner: TunerDep, request: Request) -> PlantHold:
    """Hold the plant: the tuner changes no loop's gains of its own until ``DELETE
    /hold`` (the guard's rollbacks of earlier changes and operators' actions still go
    out). Already held: who set it and since when are kept, the reason is replaced."""
    hold = tuner.set_hold(body.reason, actor_of(request))
    admin_event(tuner, request, "hold", "plant-wide hold set: %r", body.reason)
    return hold


@router.delete("", dependencies=mutating, responses={503: {}})
def delete_hold(tuner: TunerDep, request: Request) -> PlantHold:
    """Release the plant-wide hold (not held: nothing changes); loops go on from where
    they were, with no step queued while held."""
    hold = tuner.release_hold(actor_of(request))
    admin_event(tuner, request, "hold", "plant-wide hold released")
    return hold


@router.get("/history")
def hold_history(tuner: TunerDep) -> list[HoldEvent]:
    """The holds, reason changes and releases, newest first: the last 100
    (``holds.LOG_KEPT``), the last hold's own among them however many changes of its reason
    followed."""
    return tuner.hold_history()
