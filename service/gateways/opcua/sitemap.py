"""The gateway's map file (TOML): which server, how to secure it, which bus, which loops.

A site is commissioned by writing this file; ``docs/opcua.md`` has a complete example and
``pitune plant opcua --write-map`` writes the one of the simulated DCS. Node ids are
OPC UA strings with a namespace index (``ns=2;s=LIC-101.PV``, ``ns=3;i=1042``); the
``nsu=<namespace uri>`` form is not resolved (yet): read the index off the server.

Keys of ``[defaults]`` apply to every ``[[loops]]`` entry that does not set them.
Passwords and tokens never live in the file: ``password_env`` and ``token_env`` name the
environment variables that hold them.
"""

from __future__ import annotations

import math
import os
import tomllib
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

from asyncua import ua
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    field_validator,
    model_validator,
)

from service.gateways.opcua.forms import GainForm
from service.units import ScalingSpec
from service.wire.flood import MAX_SAMPLE_RATE_HZ
from service.wire.protocol import DEFAULT_PREFIX, GatewayId, LoopId


def _node_id(text: str) -> str:
    try:
        ua.NodeId.from_string(text)
    except Exception as exc:  # asyncua raises several kinds for a bad string
        raise ValueError(f"not an OPC UA node id ({type(exc).__name__}: {exc})") from None
    return text


NodeRef = Annotated[
    str,
    Field(min_length=3, max_length=512, pattern=r"^(ns|i|s|g|b)="),
    AfterValidator(_node_id),
]
ModeValue = bool | int | str
PositiveS = Annotated[float, Field(gt=0.0, le=86400.0, allow_inf_nan=False)]


class MapError(ValueError):
    """The map file is missing, not TOML, or not a valid map (the message says where)."""


class Security(StrEnum):
    none = "None"
    basic256sha256 = "Basic256Sha256"


class SecurityMode(StrEnum):
    sign = "Sign"
    sign_and_encrypt = "SignAndEncrypt"


class ServerMap(BaseModel):
    """The OPC UA server and how to talk to it."""

    model_config = ConfigDict(extra="forbid")

    url: Annotated[str, Field(pattern=r"^opc\.tcp://")]
    security: Security = Security.basic256sha256
    mode: SecurityMode = SecurityMode.sign_and_encrypt
    allow_insecure: bool = Field(
        False, description="Must be true to run with security None (commissioning, tests)."
    )
    certificate: Path | None = Field(None, description="Client certificate, DER or PEM.")
    private_key: Path | None = Field(None, description="Client private key, PEM.")
    server_certificate: Path | None = Field(
        None, description="The server's certificate (DER or PEM), pinned: required with "
        "security, unless trust_endpoint_certificate."
    )  # fmt: skip
    trust_endpoint_certificate: bool = Field(
        False, description="Take the server's certificate from its endpoint, unverified "
        "(commissioning): whoever answers at url gets the password and the gain writes."
    )  # fmt: skip
    application_uri: str = Field(
        "urn:pitune:gateway", description="Must match the URI in the client certificate."
    )
    user: str | None = Field(None, description="User name; absent: anonymous.")
    password_env: str = "PITUNE_OPCUA_PASSWORD"
    allow_plaintext_password: bool = Field(
        False, description="Must be true to log in as user with security None: the password "
        "then crosses the network readable (commissioning on a closed bench)."
    )  # fmt: skip
    timeout_s: PositiveS = 4.0
    watchdog_s: PositiveS = Field(
        5.0, description="Keep-alive probe period and timeout: a busy server that answers "
        "slower than this is taken for lost (a closed connection is noticed at once)."
    )  # fmt: skip
    reconnect_min_s: PositiveS = 0.5
    reconnect_max_s: PositiveS = 30.0
    publishing_interval_ms: float | None = Field(
        None, gt=0.0, description="Subscription publishing interval (default: the smallest "
        "sampling interval of the loops)."
    )  # fmt: skip

    @model_validator(mode="after")
    def _secure_unless_told(self) -> ServerMap:
        if self.security is Security.none:
            if not self.allow_insecure:
                raise ValueError(
                    'security "None" sends gains unauthenticated: set allow_insecure = true '
                    "in [server] to run like that anyway"
                )
            # asyncua sends the password as it is unless the server's user token policy
            # names an encryption, and then to a server certificate nothing verified
            if self.user is not None and not self.allow_plaintext_password:
                raise ValueError(
                    f'security "None" with user {self.user!r} sends its password in clear '
                    "text: use security Basic256Sha256, or set allow_plaintext_password = "
                    "true in [server] to accept that"
                )
        elif self.certificate is None or self.private_key is None:
            raise ValueError(
                f"security {self.security.value} needs certificate and private_key "
                "(pitune gateway certs makes a self-signed pair)"
            )
        elif self.server_certificate is None and not self.trust_endpoint_certificate:
            raise ValueError(
                f"security {self.security.value} needs server_certificate, the DCS server's "
                "certificate to pin: without it the gateway would take any server's "
                "certificate from the endpoint and send that server the password and the "
                "gains. Set trust_endpoint_certificate = true to run like that anyway"
            )
        return self

    def password(self) -> str | None:
        if self.user is None:
            return None
        value = os.environ.get(self.password_env)
        if value is None:
            raise MapError(f"user {self.user!r} needs its password in ${self.password_env}")
        return value


class BusMap(BaseModel):
    """The Zenoh side (the same options as ``pitune plant run``)."""

    model_config = ConfigDict(extra="forbid")

    connect: list[str] = []
    listen: list[str] = []
    mode: str | None = Field(None, pattern="^(peer|client)$")
    zenoh_config: Path | None = None
    prefix: str = DEFAULT_PREFIX
    gateway_id: GatewayId | None = Field(
        None, description="Receive batched gains on {prefix}/gateways/{id}/gains and "
        "publish the samples on {prefix}/gateways/{id}/samples (its loops must be "
        "registered with this gateway id)."
    )  # fmt: skip
    shared_samples_key: bool = Field(
        False, description="With a gateway_id, publish the samples on {prefix}/samples "
        "anyway: for loops registered without the gateway id (a per-gateway Zenoh user "
        "may not publish there)."
    )  # fmt: skip
    batch_interval_s: Annotated[float, Field(gt=0.0, le=10.0)] = 0.05
    buffer_max_samples: Annotated[int, Field(ge=1, le=10_000_000)] = 100_000

    @property
    def samples_gateway(self) -> str | None:
        """The gateway whose samples key carries the samples (None: ``{prefix}/samples``)."""
        return None if self.shared_samples_key else self.gateway_id


class TunerMap(BaseModel):
    """Optional bulk registration of the loops with the tuner's admin API at start; the
    tuner's flood limit, which the samples held through an outage are paced under."""

    model_config = ConfigDict(extra="forbid")

    register_url: str | None = None
    token_env: str = "PITUNE_API_TOKEN"
    timeout_s: PositiveS = 60.0
    max_sample_rate_hz: Annotated[float, Field(gt=0.0)] = Field(
        MAX_SAMPLE_RATE_HZ, description="The tuner's --max-sample-rate: a loop's samples "
        "go out at a quarter of it (service.gateways.backlog).",
    )  # fmt: skip


class Limits(BaseModel):
    """Hard limits of the block's P and I values, in the block's own units: a gains
    message outside them is refused, never clipped."""

    model_config = ConfigDict(extra="forbid")

    p: tuple[float, float]
    i: tuple[float, float]

    @field_validator("p", "i")
    @classmethod
    def _range(cls, value: tuple[float, float]) -> tuple[float, float]:
        lo, hi = value
        if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo <= hi):
            raise ValueError(f"limits must be 0 < low <= high, got {value}")
        return value

    def allows(self, p: float, i: float) -> bool:
        return self.p[0] <= p <= self.p[1] and self.i[0] <= i <= self.i[1]


class Registration(BaseModel):
    """What the loop is registered with (``POST /loops/bulk``); gains are read from the block."""

    model_config = ConfigDict(extra="forbid")

    scaling: ScalingSpec
    sample_period_s: float | None = Field(
        None, gt=0.0, description="Plant-clock seconds between samples (default: the "
        "sampling interval)."
    )  # fmt: skip
    extra: dict[str, Any] = Field(
        default_factory=dict, description="Other LoopConfig fields (mode, guard, forgetting)."
    )


class LoopMap(BaseModel):
    """One PI loop: its nodes, gain form, write policy and limits."""

    model_config = ConfigDict(extra="forbid")

    id: LoopId
    sp: NodeRef
    pv: NodeRef
    op: NodeRef | None = None
    mode: NodeRef | None = Field(None, description="Mode node; absent: always auto.")
    auto_values: list[ModeValue] = Field(
        default_factory=lambda: [True], description="Mode values that mean auto (or cascade)."
    )
    p: NodeRef = Field(description="The block's proportional term (gain or band).")
    i: NodeRef = Field(description="The block's integral term (reset, repeats, ki).")
    form: GainForm = GainForm()
    tuning_enable: NodeRef | bool = Field(
        False, description="A boolean node, or a fixed flag: writes only while true."
    )
    at_high_limit: NodeRef | None = None
    at_low_limit: NodeRef | None = None
    limits: Limits
    sampling_interval_ms: Annotated[float, Field(gt=0.0, le=3_600_000.0)] = 1000.0
    queue_size: Annotated[int, Field(ge=1, le=10_000)] = 10
    min_write_interval_s: Annotated[float, Field(ge=0.0, le=86400.0)] = 10.0
    registration: Registration | None = None

    def nodes(self) -> dict[str, str]:
        """field name -> node id of everything monitored."""
        fields = ("sp", "pv", "op", "mode", "p", "i", "at_high_limit", "at_low_limit")
        out = {f: getattr(self, f) for f in fields if getattr(self, f) is not None}
        if isinstance(self.tuning_enable, str):
            out["tuning_enable"] = self.tuning_enable
        return out


class SiteMap(BaseModel):
    model_config = ConfigDict(extra="forbid")

    server: ServerMap
    bus: BusMap = BusMap()
    tuner: TunerMap = TunerMap()
    loops: Annotated[list[LoopMap], Field(min_length=1)]

    @model_validator(mode="before")
    @classmethod
    def _apply_defaults(cls, data: Any) -> Any:
        if isinstance(data, dict) and "defaults" in data:
            data = dict(data)
            defaults = data.pop("defaults") or {}
            data["loops"] = [_merged(defaults, loop) for loop in data.get("loops", [])]
        return data

    @model_validator(mode="after")
    def _unique(self) -> SiteMap:
        ids = [loop.id for loop in self.loops]
        dup = sorted({i for i in ids if ids.count(i) > 1})
        if dup:
            raise ValueError(f"duplicate loop ids: {', '.join(dup)}")
        return self

    def resolve_paths(self, base: Path) -> SiteMap:
        """Relative file names in the map are relative to the map's folder."""

        def fix(p: Path | None) -> Path | None:
            return None if p is None or p.is_absolute() else base / p

        server = self.server.model_copy(
            update={
                k: fix(getattr(self.server, k)) or getattr(self.server, k)
                for k in ("certificate", "private_key", "server_certificate")
            }
        )
        bus = self.bus.model_copy(
            update={"zenoh_config": fix(self.bus.zenoh_config) or self.bus.zenoh_config}
        )
        return self.model_copy(update={"server": server, "bus": bus})


def _merged(defaults: dict, loop: Any) -> Any:
    """A loop's table over ``[defaults]``, tables key by key: a loop that sets only its
    form's spans keeps the site's gain form (a table replaced whole would fall back, without
    a word, on the built-in form)."""
    if not isinstance(loop, dict):
        return loop  # the validator says what is wrong with it
    out = dict(defaults)
    for key, value in loop.items():
        both = isinstance(value, dict) and isinstance(out.get(key), dict)
        out[key] = _merged(out[key], value) if both else value
    return out


def load_map(path: str | Path) -> SiteMap:
    """Read and validate a map file; :class:`MapError` with the reason if it is not one."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as exc:
        raise MapError(f"{path}: {exc.strerror or exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise MapError(f"{path}: not TOML: {exc}") from None
    return parse_map(data, base=path.parent, source=str(path))


def parse_map(data: dict, *, base: Path = Path("."), source: str = "map") -> SiteMap:
    from pydantic import ValidationError

    try:
        return SiteMap.model_validate(data).resolve_paths(base)
    except ValidationError as exc:
        lines = [
            f"{'.'.join(str(p) for p in err['loc']) or '(top)'}: {err['msg']}"
            for err in exc.errors()
        ]
        if len(lines) == 1:  # one line for one fault
            raise MapError(f"{source}: invalid map: {lines[0]}") from None
        raise MapError(f"{source}: invalid map:\n" + "\n".join(f"  {x}" for x in lines)) from None
