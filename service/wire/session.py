"""Network plumbing shared by the tuner, the gateways, the demo, the benchmark and tests.

One Zenoh config builder for every pitune process (:func:`session_config`) and one
free-port finder (:func:`free_port`). It lives in ``service`` because the tuner's bus
needs it and ``service`` must not import the plant simulator (``plant_sim`` already
depends on ``service.wire.protocol``).
"""

from __future__ import annotations

import json
import re
import socket
from collections.abc import Sequence
from pathlib import Path

import zenoh


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def one_line(text: object) -> str:
    """An error's text on one line, without Zenoh's Rust source locations."""
    text = re.sub(r" at /\S+\.rs:\d+\.?", "", str(text))
    return " ".join(text.split())


def join_failure(exc: Exception, where: str) -> tuple[bool, str]:
    """A Zenoh session that did not open (``where``: the endpoints' options): whether the
    command line or config is at fault (a malformed endpoint or config file: fixing it is
    the user's, trying again does not help), and the failure on one line. The tuner, the
    plant simulator and the gateways say it alike."""
    text = one_line(exc)
    lowered = text.lower()
    if any(word in lowered for word in ("endpoints must be", "invalid", "expected")):
        return True, (
            f"invalid Zenoh endpoint or config ({where}): {text}. Endpoints look like "
            "tcp/127.0.0.1:7447 or tls/router.site:7447"
        )
    return False, f"cannot join the Zenoh bus ({where}): {text}"


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
