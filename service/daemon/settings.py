"""Daemon settings: pydantic-settings from ``PITUNE_*`` variables and an optional TOML file.

Precedence, highest first: explicit values (command-line flags), environment
variables, the config file (``--config`` or ``PITUNE_CONFIG``), defaults. List values
in the environment are JSON, e.g. ``PITUNE_ZENOH_CONNECT='["tcp/10.0.0.5:7447"]'``.
"""

from __future__ import annotations

import os
import re
import socket
from contextvars import ContextVar
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

from service.wire.protocol import DEFAULT_PREFIX, LOOP_ID_PATTERN, Keys

_config_file: ContextVar[Path | None] = ContextVar("pitune_config_file", default=None)


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
    key_prefix: str = DEFAULT_PREFIX
    instance_id: Annotated[str, Field(pattern=LOOP_ID_PATTERN)] = Field(
        default_factory=default_instance_id
    )
    zenoh_mode: Literal["peer", "client", "router"] = "peer"
    zenoh_listen: list[str] = ["tcp/127.0.0.1:7447"]
    zenoh_connect: list[str] = []
    zenoh_config: Path | None = Field(
        None, description="Zenoh JSON5 config file (TLS, auth); the options above override it."
    )
    zenoh_multicast_scouting: bool = False
    db_path: Path = Path("pitune.db")
    agent_weights: str | None = Field(
        None,
        description="Agent weights file; 'untrained' for a random agent (tests only). "
        "Default: the shipped weights.",
    )
    snapshot_interval_s: Annotated[float, Field(gt=0.0)] = 30.0
    max_sample_rate_hz: Annotated[float, Field(gt=0.0)] = Field(
        1000.0,
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
    store_failure_exit_s: Annotated[float, Field(gt=0.0)] = Field(
        60.0,
        description="Seconds of failing store commits after which the daemon exits "
        "(status 74) for its supervisor to restart it from the store.",
    )
    log_level: Literal["debug", "info", "warning", "error"] = "info"

    @field_validator("api_token", mode="before")
    @classmethod
    def _blank_token_is_unset(cls, value: object) -> object:
        """``PITUNE_API_TOKEN=`` (empty, a template left unfilled) is no token: the API is
        open, as when it is unset, and says so at start-up (see :mod:`service.daemon.api`)."""
        raw = value.get_secret_value() if isinstance(value, SecretStr) else value
        return None if isinstance(raw, str) and not raw.strip() else value

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
        sources: tuple[PydanticBaseSettingsSource, ...] = (init_settings, env_settings)
        if path:
            if not Path(path).is_file():
                raise FileNotFoundError(f"config file not found: {path}")
            sources += (TomlConfigSettingsSource(settings_cls, toml_file=path),)
        return sources


def load_settings(config_file: Path | str | None = None, **overrides: object) -> Settings:
    """Settings from ``overrides`` > environment > ``config_file`` (or PITUNE_CONFIG)."""
    token = _config_file.set(Path(config_file) if config_file else None)
    try:
        return Settings(**overrides)
    finally:
        _config_file.reset(token)
