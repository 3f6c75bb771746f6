"""The Zenoh wire protocol between a plant's DCS gateway and the tuner daemon.

These pydantic models are the single source of truth for the bus: the daemon validates
with them, ``docs/protocol.md`` embeds the JSON Schemas generated from them, and
gateways or simulators written in Python can import them directly.

Key expressions, under a configurable prefix (default ``pitune``)::

    {prefix}/loops/{loop_id}/sample   gateway -> tuner   Sample
    {prefix}/samples                  gateway -> tuner   SampleBatch (many loops, one message)
    {prefix}/gateways/{gateway}/samples gateway -> tuner SampleBatch of that gateway's loops
                                                         only (revision 4: in a cluster only
                                                         their owner receives it)
    {prefix}/loops/{loop_id}/gains    tuner -> gateway   GainsMessage, one per RL step
    {prefix}/gateways/{gateway}/gains tuner -> gateway   GainsBatch (loops registered with
                                                         that gateway, one per step batch)
    {prefix}/loops/{loop_id}/state    queryable          StateReply (or ErrorReply); the
                                                         parameter ``after_t=<t>`` waits for
                                                         a sample of that loop at t or later
    {prefix}/gateways/{gateway}/state queryable          StateBatch: every loop registered
                                                         with that gateway, in one reply
    {prefix}/tuners/{instance_id}     liveliness token while a tuner is up

Payloads are JSON (``application/json``). Every message carries ``v``, the schema
version. Changes that only add optional fields keep the version; a receiver ignores
fields it does not know. A breaking change bumps the version, and a tuner rejects
samples whose ``v`` is newer than the one it speaks.

Units are the DCS's engineering units: ``e``, ``sp`` and ``pv`` in the measurement's
unit, ``kp`` in output units per measurement unit, ``ki`` in output units per
(measurement unit x second), ``t`` in seconds of the plant's clock.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import StrEnum
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

SCHEMA_VERSION = 1
SCHEMA_REVISION = 10
"""Additive revisions within :data:`SCHEMA_VERSION` (optional fields and new enum values
only, ``v`` unchanged). What each revision added: the table in docs/protocol.md,
Versioning (tests/test_tuner_protocol.py holds its title and table to this number)."""
DEFAULT_PREFIX = "pitune"
ENCODING = "application/json"
MAX_MAGNITUDE = 1e12
"""Largest absolute value any number on the wire may have; anything bigger is absurd."""
MAX_BATCH = 100_000
"""Most samples in a :class:`SampleBatch`, gains messages in a :class:`GainsBatch`."""
MAX_MESSAGE_BYTES = 32 * 1024 * 1024
"""Largest sample message (single or batch) a tuner reads: 100,000 samples of up to ~330
bytes each. A bigger one is refused unread (``too_large``)."""
EPOCH_AHEAD_MS = 86_400_000.0
"""How far ahead of a host's wall clock (ms) an epoch (its tuner's start, ms) may be: a
gateway drops a message beyond it (a forged 2**62 would order above every real update for
ever), and a tuner whose stored epoch is that far ahead starts from its clock again."""

LOOP_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$"
"""Loop and instance ids are single key-expression chunks: no '/', no wildcards."""
_ID_RE = re.compile(LOOP_ID_PATTERN)
_PREFIX_RE = re.compile(r"^[A-Za-z0-9_.\-]+(/[A-Za-z0-9_.\-]+)*$")

Number = Annotated[float, Field(ge=-MAX_MAGNITUDE, le=MAX_MAGNITUDE)]
Gain = Annotated[float, Field(strict=True, gt=0.0, le=MAX_MAGNITUDE)]
LoopId = Annotated[str, Field(pattern=LOOP_ID_PATTERN, examples=["LIC-101"])]
GatewayId = Annotated[str, Field(pattern=LOOP_ID_PATTERN, examples=["gw-north"])]
InstanceId = Annotated[str, Field(pattern=LOOP_ID_PATTERN, examples=["tuner-a"])]  # gateways log it
Version = Annotated[int, Field(ge=1, le=SCHEMA_VERSION, description="Schema version.")]


class Mode(StrEnum):
    """How a loop's gain updates are meant to be used."""

    auto = "auto"
    """Updates are meant to be applied; the tuner assumes they are."""
    advisory = "advisory"
    """Updates are published for a human to consider and never assumed applied."""
    frozen = "frozen"
    """No updates at all."""
    shadow = "shadow"
    """The agent steps and its proposals are recorded with a predicted effect; nothing is
    published (revision 3)."""


PUBLISHED_MODES = frozenset({Mode.auto, Mode.advisory})
"""The modes whose loops get gains messages (frozen and shadow loops get none)."""


class LoopStatus(StrEnum):
    """What a loop's tuning is doing right now (the safety guard's view)."""

    waiting = "waiting"
    """Registered (or reset) and no sample received yet."""
    tuning = "tuning"
    manual = "manual"
    """The gateway reports the loop in manual: tuning pauses."""
    saturated = "saturated"
    """The gateway reports the controller output saturated: tuning pauses."""
    stale = "stale"
    """No sample for several sample periods: tuning pauses."""
    quiet = "quiet"
    """No setpoint change in the last ``excitation_periods`` RL periods: tuning waits
    for one (the agent learns from setpoint responses)."""
    frozen = "frozen"
    identifying = "identifying"
    """Registered without a model hint: the tuner identifies the loop's model from its
    closed-loop data and does not tune it until it is confident of one."""
    hint_mismatch = "hint_mismatch"
    """The identified model disagrees with the scaling in force (hint) by more than the
    loop's tolerance; tuning continues with the hint (auto-rescale off)."""
    out_of_envelope = "out_of_envelope"
    """The identified dynamics, in the agent's units, are outside the region the agent was
    trained on (or integrating): tuning pauses until a rescale or a new identification."""
    oscillating = "oscillating"
    """The loop oscillates (verification's detector; revision 7): tuning pauses until the
    oscillation has died away. A change pending when it began was rolled back."""
    gains_out_of_bounds = "gains_out_of_bounds"
    """The gains the gateway reports lie outside the guard's bounds (revision 8): an
    operator's choice, or samples that do not carry the DCS's gains in pitune's parallel
    form. Tuning is held (no step, no model tuning, no rollback) until reported gains are
    within the bounds, the bounds are patched to hold them, or the loop is reset."""


class UpdateReason(StrEnum):
    agent = "agent"
    """A step of the RL agent (after the safety guard)."""
    reset = "reset"
    """An operator reset the loop to its registered gains."""
    rollback = "rollback"
    """The last-good gains restored (auto) or proposed (advisory): a change made the loop
    worse, or an operator asked for it (revision 3)."""
    accepted = "accepted"
    """An advisory proposal an operator accepted: sent as mode ``auto``, to be applied
    (revision 3)."""
    model = "model"
    """The first tuning from an identified model (a loop without a hint identified, or a
    wrong hint rescaled): gains well below the model's SIMC tuning raised to it, to be
    verified like any change (revision 5)."""


class RejectReason(StrEnum):
    """Why a sample was rejected (the ``reason`` label of the rejection metric)."""

    malformed_json = "malformed_json"
    schema = "schema"
    """Valid JSON, but a missing field or a wrong type."""
    non_finite = "non_finite"
    """NaN or +-Infinity."""
    out_of_range = "out_of_range"
    """An absurd magnitude, a gain <= 0, a negative ``applied_seq``."""
    unsupported_version = "unsupported_version"
    """A ``v`` this tuner does not read: newer, or below 1."""
    bad_key = "bad_key"
    unknown_loop = "unknown_loop"
    duplicate = "duplicate"
    """Same timestamp as the loop's last accepted sample."""
    out_of_order = "out_of_order"
    flood = "flood"
    """More samples per second on one loop than the configured limit."""
    overload = "overload"
    """The daemon's input queue is full (in messages or bytes): the message was dropped
    unread and counts as one sample, whatever it held."""
    too_large = "too_large"
    """A message over :data:`MAX_MESSAGE_BYTES`, refused unread: counts as one sample."""
    wrong_gateway = "wrong_gateway"
    """A sample on a gateway's samples key of a loop registered with another gateway
    or none (revision 4)."""
    internal = "internal"
    """The tuner failed while handling the sample (a defect: its log says which)."""


_WIRE = ConfigDict(strict=True, allow_inf_nan=False, extra="ignore", frozen=True)


class Sample(BaseModel):
    """One closed-loop sample of one loop (gateway -> tuner)."""

    model_config = ConfigDict(
        **_WIRE,
        json_schema_extra={"examples": [{"v": 1, "t": 1200.0, "sp": 55.0, "pv": 53.2}]},
    )

    v: Version = SCHEMA_VERSION
    t: Number = Field(description="Sample time, seconds on the plant's clock; strictly increasing.")
    e: Number | None = Field(None, description="Error, setpoint minus measurement.")
    sp: Number | None = Field(None, description="Setpoint (used with pv when e is absent).")
    pv: Number | None = Field(None, description="Measurement (used with sp when e is absent).")
    kp: Gain | None = Field(
        None, description="Proportional gain in force in the DCS; a change is adopted."
    )
    ki: Gain | None = Field(None, description="Integral gain in force in the DCS (per second).")
    op: Number | None = Field(
        None,
        description="Controller output (the PI's output, engineering units), for the "
        "identification of the loop's model (when absent the tuner reconstructs it from "
        "the PI law and the gains in force; in manual, the operator's output, whose steps "
        "identify the loop: a bump test), and to see an output held at a limit where "
        "the gateway cannot set saturated (unchanged while the PI law would move it: "
        "docs/identification.md, An output held at a limit).",
    )
    auto: bool = Field(True, description="False while the loop is in manual: tuning pauses.")
    saturated: bool = Field(
        False, description="True while the controller output is at a limit: tuning pauses."
    )
    applied_seq: int | None = Field(
        None,
        ge=0,
        description="seq of the last gains message the DCS has applied to this loop (0: "
        "none): the kp/ki reported are that update's, not an operator's change (revision 2).",
    )

    @model_validator(mode="after")
    def _has_error(self) -> Sample:
        if self.e is None and (self.sp is None or self.pv is None):
            raise ValueError("a sample needs either e or both sp and pv")
        return self

    @property
    def error(self) -> float:
        """Setpoint minus measurement (``e`` wins when both forms are given)."""
        return self.e if self.e is not None else self.sp - self.pv


class BatchedSample(Sample):
    """A sample inside a :class:`SampleBatch`, naming its loop."""

    loop_id: LoopId


class SampleBatch(BaseModel):
    """Samples of many loops in one message (gateways with thousands of loops)."""

    model_config = _WIRE

    v: Version = SCHEMA_VERSION
    samples: list[BatchedSample] = Field(max_length=MAX_BATCH)


class SampleColumns(BaseModel):
    """The samples of a :class:`SampleBatch` as columns, on the same keys (revision 6):
    sample ``i`` has field ``k`` = ``columns[k][i]`` (null: as that field null in the
    batch's sample, i.e. not carried for the optional numbers and ``applied_seq``);
    judged sample by sample exactly as the batch's. For gateways of thousands of loops:
    the tuner decodes it ~5x cheaper than the batch's objects."""

    model_config = _WIRE

    v: Version = SCHEMA_VERSION
    columns: dict[str, list[str | float | int | bool | None]] = Field(
        description="Field name (those of BatchedSample: loop_id and t required) -> one "
        "value per sample, every list of the same length (at most MAX_BATCH); unknown "
        "fields are ignored.",
        json_schema_extra={"examples": [{"loop_id": ["FIC101", "TIC204"], "t": [60.0, 60.0],
                                         "sp": [55.0, 80.0], "pv": [53.2, 80.4]}]},
    )  # fmt: skip

    @classmethod
    def of(cls, samples: list[BatchedSample]) -> SampleColumns:
        """``samples`` as columns: each field any of them carries, null where one does not."""
        rows = [sample.model_dump(exclude_none=True) for sample in samples]
        names = dict.fromkeys(name for row in rows for name in row)
        return cls(columns={name: [row.get(name) for row in rows] for name in names})


class GainsMessage(BaseModel):
    """New absolute gains for one loop (tuner -> gateway), published once per RL step."""

    model_config = _WIRE

    v: Version = SCHEMA_VERSION
    loop_id: LoopId
    seq: int = Field(ge=1, description="Per-loop sequence number, increasing across restarts.")
    t: float = Field(description="Plant time (s) of the sample that triggered the update.")
    dkp: float = Field(description="Change of kp, engineering units.")
    dki: float = Field(description="Change of ki, engineering units (per second).")
    kp: float = Field(gt=0.0, description="New proportional gain, engineering units.")
    ki: float = Field(gt=0.0, description="New integral gain, engineering units per second.")
    mode: Literal[Mode.auto, Mode.advisory] = Field(
        description="'advisory' updates are suggestions: the tuner never assumes them applied."
    )
    reason: UpdateReason = UpdateReason.agent
    instance_id: InstanceId = Field(description="The tuner instance that published the update.")
    epoch: int | None = Field(
        None,
        ge=1,
        description="The store's epoch: larger for every later tuner start (on the same "
        "store, or a fresh one). Order updates of a loop by (epoch, seq) (revision 2).",
    )
    why: str | None = Field(
        None,
        max_length=512,
        description="Short machine-readable reason, space-separated key=value pairs: "
        "reason, basis (model: identified, hint), dkp/dki (relative change, %), guard "
        "(none, rate, bounds), verdict (pending, rolled_back, rollback_proposed), why "
        "(of a rollback: iae, oscillation, operator), resent (takeover: a message sent again "
        "by a cluster member taking the loop over) (revision 3).",
    )


class GainsBatch(BaseModel):
    """Gains messages of many loops in one message (tuner -> a gateway fronting them).

    Loops registered with a ``gateway`` get their gains this way instead of one message
    each: every batched agent step publishes one message per gateway.
    """

    model_config = _WIRE

    v: Version = SCHEMA_VERSION
    gains: list[GainsMessage] = Field(max_length=MAX_BATCH)


class Hold(BaseModel):
    """What holds the agent's steps of a loop whose status does not say it (a loop held
    this way reads ``tuning`` while its gains stay as they are; docs/tuner.md, Status and
    holds). In :class:`StateReply` since revision 9, and in the REST loop view."""

    model_config = _WIRE

    guard: Literal["cooldown", "model_check", "plant"] = Field(
        description="'cooldown': the agent is not stepped until until_t, after a change of "
        "the tuner's own (a rollback, a rejected proposal, a model's tuning until its "
        "verdict); 'model_check': the model check has held the agent's steps since since_t "
        "(the identified model predicted them worse than guard.model_check times the "
        "model's tuning, and worse than the gains in force); 'plant': the plant-wide hold "
        "(revision 10): the tuner changes no loop's gains of its own until it is released, "
        "why says who set it, when (UTC) and why."
    )
    since_t: float | None = Field(
        None, description="Plant time of the first step of the run the model check held."
    )
    until_t: float | None = Field(None, description="Plant time the cool-down ends.")
    why: str = Field(description="The same in words, with where to look further.")


class StateReply(BaseModel):
    """Reply of the ``state`` queryable: a loop's current gains and status."""

    model_config = _WIRE

    v: Version = SCHEMA_VERSION
    loop_id: LoopId
    kp: float
    ki: float
    mode: Mode
    status: LoopStatus
    seq: int = Field(ge=0, description="Sequence number of the last gains message (0: none).")
    last_t: float | None = Field(description="Plant time (s) of the last accepted sample.")
    instance_id: InstanceId
    epoch: int | None = Field(
        None, ge=1, description="The epoch the last gains message (seq) went out under."
    )
    rl_period_s: float | None = Field(
        None, description="Plant seconds between two RL steps of this loop (revision 2)."
    )
    next_due_t: float | None = Field(
        None,
        description="Plant time at which the loop's next RL step falls due; while the "
        "status is 'tuning', an update is expected soon after a sample at or after it.",
    )
    gateway: str | None = Field(
        None,
        description="The gateway whose GainsBatch carries this loop's gains (None: "
        "its own gains key).",
    )
    hold: Hold | None = Field(
        None,
        description="What holds the agent's steps while the status may still read "
        "'tuning' (None: nothing; revision 9).",
    )
    oscillating: bool = Field(
        False,
        description="The oscillation detector flags the loop now, whatever its status "
        "(revision 9).",
    )


class StateBatch(BaseModel):
    """Reply of ``{prefix}/gateways/{gateway}/state``: the state of every loop registered
    with that gateway, in one message (revision 2)."""

    model_config = _WIRE

    v: Version = SCHEMA_VERSION
    gateway: GatewayId
    instance_id: InstanceId
    epoch: int | None = Field(None, ge=1)
    states: list[StateReply]


class ErrorReply(BaseModel):
    """Error reply of the ``state`` queryable (e.g. unknown loop)."""

    model_config = _WIRE

    v: Version = SCHEMA_VERSION
    loop_id: str
    error: str


WIRE_MODELS: tuple[type[BaseModel], ...] = (
    Sample,
    SampleBatch,
    SampleColumns,
    GainsMessage,
    GainsBatch,
    StateReply,
    StateBatch,
    ErrorReply,
)


def is_valid_id(value: str) -> bool:
    """Whether ``value`` can be a loop or instance id (one key-expression chunk)."""
    return bool(_ID_RE.fullmatch(value))


@dataclass(frozen=True)
class Keys:
    """Key expressions of the protocol under one prefix."""

    prefix: str = DEFAULT_PREFIX

    def __post_init__(self) -> None:
        if not _PREFIX_RE.fullmatch(self.prefix):
            raise ValueError(f"invalid key prefix {self.prefix!r}: chunks of [A-Za-z0-9_.-]")

    def sample(self, loop_id: str) -> str:
        return f"{self.prefix}/loops/{loop_id}/sample"

    def gains(self, loop_id: str) -> str:
        return f"{self.prefix}/loops/{loop_id}/gains"

    def state(self, loop_id: str) -> str:
        return f"{self.prefix}/loops/{loop_id}/state"

    def gateway_gains(self, gateway: str) -> str:
        return f"{self.prefix}/gateways/{gateway}/gains"

    def gateway_state(self, gateway: str) -> str:
        return f"{self.prefix}/gateways/{gateway}/state"

    def gateway_samples(self, gateway: str) -> str:
        """The key of a gateway's SampleBatch messages (revision 4)."""
        return f"{self.prefix}/gateways/{gateway}/samples"

    @property
    def all_gateway_samples(self) -> str:
        return self.gateway_samples("*")

    @property
    def all_gateway_states(self) -> str:
        return self.gateway_state("*")

    def gateway_id(self, key: str) -> str | None:
        """The gateway in ``{prefix}/gateways/{gateway}/{kind}``, or None."""
        return self._id_in(key, "gateways")

    def tuner(self, instance_id: str) -> str:
        return f"{self.prefix}/tuners/{instance_id}"

    @property
    def batch(self) -> str:
        return f"{self.prefix}/samples"

    @property
    def all_samples(self) -> str:
        return self.sample("*")

    @property
    def all_gains(self) -> str:
        return self.gains("*")

    @property
    def all_states(self) -> str:
        return self.state("*")

    @property
    def all_tuners(self) -> str:
        return self.tuner("*")

    def loop_id(self, key: str) -> str | None:
        """The loop id in ``{prefix}/loops/{loop_id}/{kind}``, or None if ``key`` is not one."""
        return self._id_in(key, "loops")

    def _id_in(self, key: str, kind: str) -> str | None:
        """The id chunk of ``{prefix}/{kind}/{id}/{what}``, or None if ``key`` is not one."""
        head = f"{self.prefix}/{kind}/"
        parts = key[len(head) :].split("/") if key.startswith(head) else []
        return parts[0] if len(parts) == 2 and is_valid_id(parts[0]) else None


def encode(message: BaseModel) -> bytes:
    """JSON bytes of a wire message."""
    return message.model_dump_json().encode()
