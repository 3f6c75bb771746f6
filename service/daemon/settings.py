"""Daemon settings: pydantic-settings from ``PITUNE_*`` variables and an optional TOML file.

Precedence, highest first: explicit values (command-line flags), environment
variables, the config file (``--config`` or ``PITUNE_CONFIG``), defaults. List values
in the environment are JSON or comma-separated, e.g.
``PITUNE_ZENOH_CONNECT='["tcp/10.0.0.5:7447"]'`` or
``PITUNE_ZENOH_CONNECT=tcp/10.0.0.5:7447,tcp/10.0.0.6:7447``. Choices are taken in any
case (``PITUNE_LOG_LEVEL=INFO``). ``PITUNE_DB`` is an alias of ``PITUNE_DB_PATH``; any
other ``PITUNE_*`` variable the tuner does not know is reported by
:func:`unknown_variables` (the daemon warns, naming the closest setting).
"""

from __future__ import annotations

import difflib
import json
import os
import re
import socket
from collections.abc import Mapping
from contextvars import ContextVar
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, SecretStr, ValidationInfo, field_validator
from pydantic.fields import FieldInfo
from pydantic_settings import (
    BaseSettings,
    NoDecode,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

from service.wire.flood import MAX_SAMPLE_RATE_HZ
from service.wire.protocol import (
    DEFAULT_PREFIX,
    LOOP_ID_PATTERN,
    Keys,
    is_valid_id,
)

_config_file: ContextVar[Path | None] = ContextVar("pitune_config_file", default=None)
ENV_PREFIX = "PITUNE_"
ENV_ALIASES = {"PITUNE_DB": "db_path"}
"""Other names accepted for a setting's variable (the flag is ``--db``)."""
OTHER_VARIABLES = frozenset(
    {
        "PITUNE_CONFIG",  # the config file
        # read by other pitune programs or by deploy/docker-compose.yml, not the tuner
        "PITUNE_API_BIND",
        "PITUNE_API_HOST_PORT",
        "PITUNE_ZENOH_BIND",
        "PITUNE_ZENOH_HOST_PORT",
        "PITUNE_ZENOH_SECRETS",
        "PITUNE_TLS_DIR",
        "PITUNE_OPCUA_PASSWORD",
        # deploy/docker-compose.ha.yml's, and the smoke script's
        "PITUNE_API2_HOST_PORT",
        "PITUNE_POSTGRES_PASSWORD",
        "PITUNE_SMOKE_LOG",
    }
)
POSTGRES_SCHEMES = ("postgresql://", "postgres://")
UNTRAINED = "untrained"
"""``agent_weights`` of a random agent (tests only)."""
SQLITE_INT_MAX = 2**63 - 1
"""Largest integer SQLite stores (a row count beyond it fails every retention pass)."""
NONE_WORDS = frozenset({"none", "null"})
"""What an optional history setting takes for "no limit" / "no archive" (any case): the
environment has no null, nor has TOML (``history_max_age_days = "none"`` in the file).
Not the empty text: a template left unfilled must not lift the store's bound."""
Endpoints = Annotated[list[str], NoDecode]
"""Zenoh endpoints: a list, or in the environment JSON or a comma-separated list."""


def default_instance_id() -> str:
    """Host name and process id, made a valid key-expression chunk."""
    host = re.sub(r"[^A-Za-z0-9_.\-]", "-", socket.gethostname()).strip("-.") or "host"
    return f"{host[:48]}-{os.getpid()}"


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="PITUNE_", extra="forbid")

    api_host: str = "127.0.0.1"
    api_port: Annotated[int, Field(ge=0, le=65535)] = 8750
    api_token: SecretStr | None = Field(
        None, description="When set, mutating REST calls need 'Authorization: Bearer <token>'."
    )
    api_gateway_tokens: dict[str, SecretStr] = Field(
        {},
        description="Gateway id -> a token that may only register loops of that gateway "
        "(POST /loops and /loops/bulk, every loop's 'gateway' that id): what a gateway "
        "host holds instead of the admin token, each its own (not another gateway's, not "
        "the admin token). In the environment a JSON object.",
    )
    api_allowed_hosts: list[str] | None = Field(
        None,
        description="Host names the admin API answers to (the Host header, without its "
        "port); others get a 400 (DNS rebinding). Default: the loopback names when api_host "
        "is loopback, any otherwise. Behind a trusted proxy (api_trusted_proxies) that "
        "forwards its scheme (X-Forwarded-Proto), a browser's Origin naming one of them "
        "is the API's own. In the environment a JSON list.",
    )
    api_trusted_proxies: list[str] = Field(
        [],
        description="Addresses of reverse proxies whose X-Forwarded-For and "
        "X-Forwarded-Proto the admin API believes (the client address it logs and audits, "
        "https for the console's Secure cookie). Default: none, not even loopback. In the "
        "environment a JSON list.",
    )
    key_prefix: str = DEFAULT_PREFIX
    instance_id: Annotated[str, Field(pattern=LOOP_ID_PATTERN)] = Field(
        default_factory=default_instance_id
    )
    zenoh_mode: Literal["peer", "client", "router"] = "peer"
    zenoh_listen: Endpoints = Field(
        ["tcp/127.0.0.1:7447"], description="Zenoh endpoints to listen on."
    )
    zenoh_connect: Endpoints = Field(
        [], description="Zenoh endpoints (routers or peers) to connect to."
    )
    zenoh_config: Path | None = Field(
        None, description="Zenoh JSON5 config file (TLS, auth); the options above override it."
    )
    zenoh_multicast_scouting: bool = False
    db_path: Path | str = Field(
        Path("pitune.db"),
        description="SQLite database (also PITUNE_DB); one tuner at a time owns it "
        "(a lock on <db>.lock). Or a PostgreSQL URL (postgresql://user@host/db): several "
        "tuners share it, each owning a part of the loops (docs/deploy.md, High availability).",
    )
    cluster_lease_s: Annotated[float, Field(ge=2.0, le=60.0)] = Field(
        5.0,
        description="With a PostgreSQL store: seconds a member's leases last without "
        "renewal (renewed every lease/5); a dead member's loops move after at most this. "
        "At most the Zenoh session's transport lease (transport/link/tx/lease, 10 s by "
        "default), or the tuner refuses to start (service/daemon/leasecheck.py).",
    )
    cluster_url: str | None = Field(
        None,
        description="With a PostgreSQL store: the admin API's URL as the other members "
        "reach it (requests for loops this tuner owns are forwarded there). "
        "Default: http://{api_host}:{api_port}.",
    )
    agent_weights: str | None = Field(
        None,
        description="Agent weights file; 'untrained' for a random agent (tests only). "
        "Default: the shipped weights.",
    )
    snapshot_interval_s: Annotated[float, Field(gt=0.0)] = 30.0
    max_sample_rate_hz: Annotated[float, Field(gt=0.0)] = Field(
        MAX_SAMPLE_RATE_HZ,
        description="Per-loop samples per second (wall clock) above which samples are "
        "rejected as a flood; accelerated simulations may need more.",
    )
    queue_size: Annotated[int, Field(ge=1)] = 200_000
    max_batch: Annotated[int, Field(ge=1)] = Field(
        20_000, description="Most bus messages handled per worker iteration."
    )
    inference_threads: Annotated[int, Field(ge=1, le=64)] = Field(
        1,
        description="torch CPU threads. Batches are small and latency-bound; one thread "
        "avoids contention with the Zenoh runtime and the HTTP server.",
    )
    inference_workers: Annotated[int, Field(ge=1, le=64)] = Field(
        1,
        description="Threads stepping one large batch (>= 2,048 due loops) in halves; "
        "2 on a 2-core box tuning a large site.",
    )
    inference_precision: Literal["auto", "float32", "bfloat16"] = Field(
        "auto",
        description="Arithmetic of the GRU's GEMMs: bfloat16 (oneDNN, AMX) is 4-5x faster "
        "where the CPU has native bfloat16 and tunes as well; auto picks it there.",
    )
    identify_hinted_loops: bool = Field(
        True,
        description="Identify loops registered with a hint too, their hints checked "
        "(guard.identify left unset): a hint 2x off in K or tau is flagged, and rescaled "
        "with auto_rescale. It costs memory and CPU per loop on the move (capped by "
        "identify_cpu_share): docs/identification.md.",
    )
    auto_rescale: bool = Field(
        False,
        description="Rescale a loop whose identified model disagrees with its hint "
        "(guard.auto_rescale left unset); off: flagged only.",
    )
    identify_cpu_share: Annotated[float, Field(gt=0.0, le=1.0)] = Field(
        0.25,
        description="Share of one core identification's model fits may take (7-20 ms "
        "each); assessments beyond it wait their turn, loops without a model first. "
        "Keeps the samples' latency when thousands of identified loops move at once.",
    )
    store_failure_exit_s: Annotated[float, Field(gt=0.0)] = Field(
        60.0,
        description="Seconds of failing store commits after which the daemon exits "
        "(status 74) for its supervisor to restart it from the store.",
    )
    epoch_reset: bool = Field(
        False,
        description="Start again from the clock when the store's epoch is more than a day "
        "ahead of it (else the start is refused, status 2). Only for one start after "
        "fixing a clock that WAS ahead; then restart the gateways (docs/deploy.md, Clocks).",
    )
    log_level: Literal["debug", "info", "warning", "error"] = Field(
        "info", description="Least severe log level written (any case)."
    )
    log_format: Literal["text", "json"] = Field(
        "text",
        description="Log lines as text (timestamp, level, logger, message) or JSON lines.",
    )

    @field_validator("log_level", "log_format", "zenoh_mode", "inference_precision", mode="before")
    @classmethod
    def _any_case(cls, value: object) -> object:
        """``INFO``, ``Info`` and ``info`` are the same choice (``warn``: ``warning``)."""
        if isinstance(value, str):
            value = value.strip().lower()
            return "warning" if value == "warn" else value
        return value

    @field_validator("zenoh_listen", "zenoh_connect", mode="before")
    @classmethod
    def _endpoint_list(cls, value: object) -> object:
        """A JSON list or a comma-separated list of endpoints (the environment's text)."""
        if not isinstance(value, str):
            return value
        text = value.strip()
        if text.startswith("["):
            try:
                return json.loads(text)
            except json.JSONDecodeError as exc:
                raise ValueError(f"not a JSON list of endpoints: {exc}") from None
        return [part.strip() for part in text.split(",") if part.strip()]

    @field_validator("db_path", mode="before")
    @classmethod
    def _path_or_url(cls, value: object) -> object:
        """A PostgreSQL URL stays text (a Path would fold its ``//``); else a path."""
        if isinstance(value, str) and not value.startswith(POSTGRES_SCHEMES):
            return Path(value)
        return value

    @property
    def postgres(self) -> bool:
        """The store is PostgreSQL (shared by a cluster of tuners), not an SQLite file."""
        return isinstance(self.db_path, str)

    @field_validator("api_token", mode="before")
    @classmethod
    def _blank_token_is_unset(cls, value: object) -> object:
        """``PITUNE_API_TOKEN=`` (empty, a template left unfilled) is no token: the API is
        open, as when it is unset, and says so at start-up (see :mod:`service.daemon.api`)."""
        raw = value.get_secret_value() if isinstance(value, SecretStr) else value
        return None if isinstance(raw, str) and not raw.strip() else value

    @field_validator("api_gateway_tokens")
    @classmethod
    def _own_tokens(
        cls, tokens: dict[str, SecretStr], info: ValidationInfo
    ) -> dict[str, SecretStr]:
        """Each key a gateway id (no registration could name another: its token would be
        useless), each token a gateway's own: not empty, not another gateway's (the gate
        would take it for one of them), not the admin token (the gate checks that first:
        the gateway would be an admin). The messages name gateways, never a token."""
        owner: dict[str, str] = {}
        admin = info.data.get("api_token")
        for gateway, token in tokens.items():
            secret = token.get_secret_value()
            if not is_valid_id(gateway):
                raise ValueError(
                    f"{gateway!r} is not a gateway id (1-64 letters, digits, '_', '.', '-', "
                    "the first a letter or digit)"
                )
            if not secret.strip():
                raise ValueError(f"gateway {gateway!r} has an empty token")
            if secret in owner:
                raise ValueError(
                    f"gateways {owner[secret]!r} and {gateway!r} have the same token: give "
                    "each gateway its own"
                )
            if admin is not None and secret == admin.get_secret_value():
                raise ValueError(
                    f"the token of gateway {gateway!r} is the admin token (PITUNE_API_TOKEN), "
                    "which may do anything: give the gateway a token of its own"
                )
            owner[secret] = gateway
        return tokens

    @field_validator(
        "history_max_rows_per_loop", "history_max_age_days", "history_archive", mode="before"
    )
    @classmethod
    def _none_word(cls, value: object) -> object:
        """``none`` or ``null`` (:data:`NONE_WORDS`) is no limit / no archive."""
        if isinstance(value, str) and value.strip().lower() in NONE_WORDS:
            return None
        return value

    @field_validator("key_prefix")
    @classmethod
    def _valid_prefix(cls, value: str) -> str:
        Keys(value)
        return value

    @property
    def keys(self) -> Keys:
        return Keys(self.key_prefix)

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        path = _config_file.get() or os.environ.get("PITUNE_CONFIG")
        sources: tuple[PydanticBaseSettingsSource, ...] = (
            init_settings,
            env_settings,
            _AliasEnvSource(settings_cls),
        )
        if path:
            if not Path(path).is_file():
                raise FileNotFoundError(f"config file not found: {path}")
            sources += (TomlConfigSettingsSource(settings_cls, toml_file=path),)
        return sources

    # -- retention of the audit (gains) history: see service/daemon/store.py ----------
    history_max_rows_per_loop: Annotated[int, Field(ge=1, le=SQLITE_INT_MAX)] | None = Field(
        10_000,
        description="Audit rows kept per registered loop, newest first (~130 bytes each; "
        "10,000 is ~19 days of a loop stepped every 165 s); 'none': no row limit.",
    )
    history_max_age_days: Annotated[float, Field(gt=0.0)] | None = Field(
        365.0,
        description="Audit rows older than this are pruned (the newest of each loop "
        "is kept); 'none': no age limit.",
    )
    history_max_rows_deleted: Annotated[int, Field(ge=1, le=SQLITE_INT_MAX)] = Field(
        100, description="Audit rows kept of a deleted loop (its newest, with its last seq)."
    )
    history_archive: Path | None = Field(
        None,
        description="JSON-lines file the pruned audit rows are appended to (fsynced) "
        "before they are deleted; 'none' (the default): pruned rows are gone (export them "
        "first with 'pitune store export'). Its folder must exist.",
    )
    history_prune_interval_s: Annotated[float, Field(gt=0.0)] = Field(
        3600.0, description="Seconds between two retention passes over the audit history."
    )
    clock_speed: Annotated[float, Field(gt=0.0, le=1e5)] = Field(
        1.0,
        description="Benchmarks only: the tuner's clock (audit wall_time, retention horizon "
        "and passes; a cluster's horizon is the database's clock) runs this many times "
        "faster than real time (pitune bench retention); 1: real time.",
    )
    monitoring: bool = Field(
        True,
        description="Benchmarks only: false turns every loop's performance figures, "
        "oscillation detector and verdicts (verify-or-rollback) off, to measure what they "
        "cost (pitune bench --monitor-ab); true in production.",
    )
    queue_bytes: Annotated[int, Field(ge=1 << 20)] = Field(
        128 * 1024 * 1024,
        description="Payload bytes the input queue holds at most (beside queue_size messages); "
        "a message that does not fit is dropped and counted.",
    )


class _AliasEnvSource(PydanticBaseSettingsSource):
    """:data:`ENV_ALIASES`: below the settings' own variables, above the config file."""

    def get_field_value(self, field: FieldInfo, field_name: str) -> tuple[Any, str, bool]:
        return None, field_name, False

    def __call__(self) -> dict[str, Any]:
        values: dict[str, Any] = {}
        for variable, field in ENV_ALIASES.items():
            own = ENV_PREFIX + field.upper()
            if variable in os.environ and own not in os.environ:
                values[field] = os.environ[variable]
        return values


def setting_variables() -> dict[str, str]:
    """Each setting's environment variable -> its field name."""
    return {ENV_PREFIX + name.upper(): name for name in Settings.model_fields}


def unknown_variables(environ: Mapping[str, str] | None = None) -> list[str]:
    """One message per ``PITUNE_*`` variable the tuner does not read, with the closest
    setting's variable when one is close (a typo, or a name from another program)."""
    environ = os.environ if environ is None else environ
    known = setting_variables()
    messages = []
    for name in sorted(environ):
        if (
            not name.startswith(ENV_PREFIX)
            or name in known
            or name in ENV_ALIASES
            or name in OTHER_VARIABLES
            or name.startswith("PITUNE_TEST_")
        ):
            continue
        close = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
        hint = f"; did you mean {close[0]}?" if close else ""
        messages.append(f"environment variable {name} is not a tuner setting, ignored{hint}")
    return messages


def load_settings(config_file: Path | str | None = None, **overrides: object) -> Settings:
    """Settings from ``overrides`` > environment > ``config_file`` (or PITUNE_CONFIG)."""
    token = _config_file.set(Path(config_file) if config_file else None)
    try:
        return Settings(**overrides)
    finally:
        _config_file.reset(token)
