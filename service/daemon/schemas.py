"""REST schemas of the admin API beyond the engine's own models (pages, audit, health).

Loop registration and views are the engine's models (:mod:`service.engine.config`).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

from service.engine.config import LoopView
from service.wire.protocol import Mode

MAX_BULK = 100_000
"""Most loops in one ``POST /loops/bulk``."""


class BulkRegistered(BaseModel):
    """Reply of ``POST /loops/bulk``."""

    registered: list[str] = Field(description="Ids of the loops registered, in request order.")


class Taken(BaseModel):
    """Reply of a registration (``POST /loops``, ``/loops/bulk``) whose ids are taken (409)."""

    detail: str
    gateways: dict[str, str | None] = Field(
        description="Each taken id (the first 5 of a bulk) -> the gateway its loop is "
        "registered with (null: none): a gateway tells its own loop, registered before a "
        "restart, from another gateway's of the same id (under which its own would never "
        "be tuned: its samples on its gateway's key are rejected wrong_gateway). The "
        "gateway's id is all a gateway's token learns here of another gateway's loop."
    )


AuditReason = Literal[
    "registered", "agent", "reset", "adopted", "patched", "deleted", "fault",
    "verified", "rollback", "verdict", "accepted", "rejected",
    "identify", "identified", "rescaled", "mismatch", "out_of_envelope", "in_envelope",
    "refuted", "model", "oscillating", "output_held",
]  # fmt: skip


class AuditEntry(BaseModel):
    """One change of a loop's gains or configuration."""

    id: int
    loop_id: str
    wall_time: float = Field(description="Unix time the change was recorded.")
    t: float | None = Field(description="Plant time (s), when the change came from a sample.")
    seq: int
    mode: Mode
    reason: AuditReason
    kp_old: float | None
    ki_old: float | None
    kp_new: float | None
    ki_new: float | None
    detail: str = ""
    verdict: str | None = Field(
        None,
        description="Of a change of the gains in force: verified, rolled_back, "
        "rollback_proposed, worse or pending (None: not a change, or judged before the "
        "rows read; docs/tuner.md, Performance and verification).",
    )


MAX_PAGE = 1000
"""Most loops or audit entries in one page of ``GET /loops`` or a loop's history."""


class LoopsPage(BaseModel):
    items: list[LoopView] = Field(description="In registration order.")
    total: int = Field(description="Loops registered.")
    offset: int
    limit: int


class HistoryPage(BaseModel):
    items: list[AuditEntry] = Field(description="Newest first.")
    total: int
    offset: int
    limit: int


class Health(BaseModel):
    status: Literal["ok", "starting", "disconnected", "failing"]
    detail: str = ""
