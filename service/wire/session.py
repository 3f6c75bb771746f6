"""Network plumbing shared by the tuner, the gateways, the demo, the benchmark and tests.

One Zenoh config builder for every pitune process (:func:`session_config`) and one
free-port finder (:func:`free_port`). It lives in ``service`` because the tuner's bus
needs it and ``service`` must not import the plant simulator (``plant_sim`` already
depends on ``service.wire.protocol``).
"""

from __future__ import annotations

import json
import socket
from collections.abc import Sequence
from pathlib import Path

import zenoh


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def session_config(
    *,
    config_file: str | Path | None = None,
    mode: str | None = None,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    multicast_scouting: bool | None = None,
) -> zenoh.Config:
    """A Zenoh config: the JSON5 ``config_file`` if given, then every option not None.

    An option left None keeps the file's value (Zenoh's default without a file), with
    one exception: without a file, multicast scouting is off unless asked for, so
    pitune processes never discover strangers on the network. With a file, the file's
    TLS, user/password and scouting sections stay in charge of what it sets.
    """
    config = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
    if multicast_scouting is None and config_file is None:
        multicast_scouting = False
    values = {
        "mode": mode,
        "listen/endpoints": None if listen is None else list(listen),
        "connect/endpoints": None if connect is None else list(connect),
        "scouting/multicast/enabled": multicast_scouting,
    }
    for path, value in values.items():
        if value is not None:
            config.insert_json5(path, json.dumps(value))
    return config
