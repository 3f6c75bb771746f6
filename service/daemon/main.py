"""``pitune tuner``: run the tuner daemon (Zenoh bus + admin API) until SIGTERM or SIGINT.

uvicorn turns SIGTERM into a graceful shutdown, which runs the app's lifespan exit:
the tuner undeclares its Zenoh entities, closes the session and snapshots its state.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys

import uvicorn
from pydantic import ValidationError

from service.daemon.settings import Settings, load_settings

# flag -> settings field; flags left out fall back to environment, config file, defaults
FLAGS = {
    "api_host": ("--api-host", {"metavar": "HOST"}),
    "api_port": ("--api-port", {"type": int, "metavar": "PORT"}),
    "zenoh_listen": ("--listen", {"action": "append", "metavar": "ENDPOINT"}),
    "zenoh_connect": ("--connect", {"action": "append", "metavar": "ENDPOINT"}),
    "zenoh_config": ("--zenoh-config", {"metavar": "FILE"}),
    "zenoh_mode": ("--zenoh-mode", {"choices": ["peer", "client", "router"]}),
    "db_path": ("--db", {"metavar": "PATH"}),
    "key_prefix": ("--prefix", {"metavar": "PREFIX"}),
    "instance_id": ("--instance-id", {"metavar": "ID"}),
    "agent_weights": ("--agent-weights", {"metavar": "FILE|untrained"}),
    "snapshot_interval_s": ("--snapshot-interval", {"type": float, "metavar": "SECONDS"}),
    "max_sample_rate_hz": ("--max-sample-rate", {"type": float, "metavar": "HZ"}),
    "inference_threads": ("--inference-threads", {"type": int, "metavar": "N"}),
    "inference_workers": ("--inference-workers", {"type": int, "metavar": "N"}),
    "inference_precision": ("--inference-precision", {"choices": ["auto", "float32", "bfloat16"]}),
    "log_level": ("--log-level", {"choices": ["debug", "info", "warning", "error"]}),
}
HELP = {
    "zenoh_listen": "Zenoh endpoint to listen on (repeatable), default tcp/127.0.0.1:7447",
    "zenoh_connect": "Zenoh endpoint (router or peer) to connect to (repeatable)",
    "zenoh_config": "Zenoh JSON5 config file (TLS, user/password); flags override it",
    "db_path": "SQLite database, default ./pitune.db",
    "key_prefix": "key-expression prefix, default 'pitune'",
    "agent_weights": "agent weights file, or 'untrained' (tests); default: the shipped weights",
    "snapshot_interval_s": "seconds between snapshots of the agent states, default 30",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", help="TOML settings file (also PITUNE_CONFIG)")
    for field, (flag, options) in FLAGS.items():
        parser.add_argument(
            flag,
            dest=field,
            default=argparse.SUPPRESS,
            help=f"{HELP.get(field) or _description(field)} [env PITUNE_{field.upper()}]",
            **options,
        )


def _description(field: str) -> str:
    return Settings.model_fields[field].description or field.replace("_", " ")


def run(args: argparse.Namespace) -> int:
    overrides = {field: getattr(args, field) for field in FLAGS if hasattr(args, field)}
    try:
        settings = load_settings(args.config, **overrides)
    except (ValidationError, FileNotFoundError) as exc:
        print(f"pitune tuner: invalid settings: {exc}", file=sys.stderr)
        return 2
    logging.basicConfig(
        level=settings.log_level.upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    import torch  # heavy: only once the settings are good

    from service.daemon.api import create_app

    torch.set_num_threads(settings.inference_threads)

    server = uvicorn.Server(
        uvicorn.Config(
            create_app(settings),
            host=settings.api_host,
            port=settings.api_port,
            log_level=settings.log_level,
            lifespan="on",
        )
    )
    # uvicorn shuts down gracefully on SIGTERM, then re-raises the signal with the handler
    # it found installed; make that a clean exit so supervisors see status 0, not -15.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0 if server.started else 1))
    server.run()
    return 0 if server.started else 1
