"""``pitune tuner``: run the tuner daemon (Zenoh bus + admin API) until SIGTERM or SIGINT.

Start-up checks what can fail before anything is opened, cheapest first, and a
failure ends in ONE line on stderr (or in the log's format once logging is set up)
saying what failed and what to do, with an exit status of :data:`EXIT_CODES`:
settings, the files they name, the store's lock (one tuner per database: a lock on
``<db>.lock`` that dies with the process), the admin API's socket (bound before the
tuner joins the bus, so a port in use never leaves a half-started tuner on Zenoh),
then the tuner itself (agent, store, Zenoh session). ``--log-level debug`` adds the
traceback.

uvicorn turns SIGTERM into a graceful shutdown, which runs the app's lifespan exit:
the tuner undeclares its Zenoh entities, closes the session and snapshots its state.
"""

from __future__ import annotations

import argparse
import errno
import fcntl
import logging
import os
import signal
import socket
import sqlite3
import sys
import time
import tomllib
from pathlib import Path

import uvicorn
from pydantic import ValidationError
from pydantic_settings import SettingsError

from service.daemon import logs
from service.daemon.leasecheck import lease_mismatch
from service.daemon.settings import (
    UNTRAINED,
    Settings,
    load_settings,
    setting_variables,
    unknown_variables,
)
from service.wire.session import join_failure, one_line

log = logging.getLogger("pitune.tuner")

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USAGE = 2
EXIT_NO_INPUT = 66
EXIT_UNAVAILABLE = 69
EXIT_CANT_CREATE = 73
EXIT_STORE_FAILED = 74  # service.daemon.delivery.EXIT_STORE_FAILED
EXIT_LOCKED = 75
EXIT_CODES = {
    EXIT_OK: "stopped by SIGTERM or SIGINT after a clean shutdown",
    EXIT_FAILED: "an unexpected error (the log has the traceback)",
    EXIT_USAGE: "invalid command line or settings (flag, PITUNE_* variable, config file "
    "value or syntax, Zenoh endpoint syntax), or a stored epoch a day ahead of the clock",
    EXIT_NO_INPUT: "a file the settings name is missing or unreadable (config file, "
    "Zenoh config, agent weights)",
    EXIT_UNAVAILABLE: "an address cannot be bound: the API port or a Zenoh listen port "
    "in use, or an address not on this host",
    EXIT_CANT_CREATE: "the store cannot be opened (--db is a directory, no permission, "
    "not an SQLite database, PostgreSQL unreachable, a schema of a newer pitune), or the "
    "history archive cannot be appended to",
    EXIT_STORE_FAILED: "the store failed to commit for store_failure_exit_s while running "
    "(restart it: it resumes from the store)",
    EXIT_LOCKED: "another tuner owns the store (its <db>.lock is held), or runs on the "
    "bus with the same key prefix",
}
PREFIX_LEASE_S = 12.0
"""How long a tuner waits at start-up for another tuner's liveliness token on its key
prefix to go: longer than Zenoh's default lease (10 s), after which the token of a tuner
killed moments ago (a supervisor's restart) has expired."""

# flag -> settings field; flags left out fall back to environment, config file, defaults
FLAGS = {
    "api_host": ("--api-host", {"metavar": "HOST"}),
    "api_port": ("--api-port", {"type": int, "metavar": "PORT"}),
    "zenoh_listen": ("--listen", {"action": "append", "metavar": "ENDPOINT"}),
    "zenoh_connect": ("--connect", {"action": "append", "metavar": "ENDPOINT"}),
    "zenoh_config": ("--zenoh-config", {"metavar": "FILE"}),
    "zenoh_mode": ("--zenoh-mode", {"type": str.lower, "choices": ["peer", "client", "router"]}),
    "db_path": ("--db", {"metavar": "PATH"}),
    "key_prefix": ("--prefix", {"metavar": "PREFIX"}),
    "instance_id": ("--instance-id", {"metavar": "ID"}),
    "agent_weights": ("--agent-weights", {"metavar": "FILE|untrained"}),
    "snapshot_interval_s": ("--snapshot-interval", {"type": float, "metavar": "SECONDS"}),
    "max_sample_rate_hz": ("--max-sample-rate", {"type": float, "metavar": "HZ"}),
    "inference_threads": ("--inference-threads", {"type": int, "metavar": "N"}),
    "inference_workers": ("--inference-workers", {"type": int, "metavar": "N"}),
    "inference_precision": (
        "--inference-precision",
        {"type": str.lower, "choices": ["auto", "float32", "bfloat16"]},
    ),
    "log_level": (
        "--log-level",
        {"type": str.lower, "choices": ["debug", "info", "warning", "error"]},
    ),
    "log_format": ("--log-format", {"type": str.lower, "choices": ["text", "json"]}),
}
HELP = {
    "zenoh_listen": "Zenoh endpoint to listen on (repeatable)",
    "zenoh_connect": "Zenoh endpoint (router or peer) to connect to (repeatable)",
    "zenoh_config": "Zenoh JSON5 config file (TLS, user/password); flags override it",
    "db_path": "SQLite database, owned by one tuner at a time; or a PostgreSQL URL "
    "(postgresql://user@host/db) shared by a cluster of tuners",
    "key_prefix": "key-expression prefix of every topic",
    "instance_id": "this tuner's id on the bus",
    "agent_weights": "agent weights file, or 'untrained' (tests)",
    "snapshot_interval_s": "seconds between snapshots of the agent states",
    "api_host": "address of the admin API",
    "api_port": "port of the admin API",
}
DEFAULT_TEXT = {
    "instance_id": "{hostname}-{pid}",
    "agent_weights": "the shipped weights",
    "api_token": "unset: the API is open",
    "zenoh_config": "none",
}


def default_text(field: str) -> str:
    """A setting's default as ``--help`` and the docs show it."""
    if field in DEFAULT_TEXT:
        return DEFAULT_TEXT[field]
    value = Settings.model_fields[field].default
    if isinstance(value, list):
        return ",".join(value) or "none"
    return str(value)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", metavar="FILE", help="TOML settings file [env PITUNE_CONFIG]")
    for field, (flag, options) in FLAGS.items():
        parser.add_argument(
            flag,
            dest=field,
            default=argparse.SUPPRESS,
            help=f"{HELP.get(field) or _description(field)} [env PITUNE_{field.upper()}] "
            f"(default: {default_text(field)})".replace("%", "%%"),
            **options,
        )
    rows = []
    for variable, field in setting_variables().items():
        flag = FLAGS[field][0] if field in FLAGS else ""
        rows.append(f"  {variable:<32} {flag or '(no flag)':<24} {default_text(field)}")
    parser.epilog = (
        "Every setting (precedence: flag > environment > --config file > default;\n"
        "lists in the environment as JSON or comma-separated; PITUNE_DB = PITUNE_DB_PATH):\n"
        f"  {'variable':<32} {'flag':<24} default\n"
        + "\n".join(rows)
        + "\n\nExit status:\n"
        + "\n".join(f"  {code:>3}  {text}" for code, text in EXIT_CODES.items())
        + "\n\nSee docs/tuner.md."
    ).replace("%", "%%")


def _description(field: str) -> str:
    return Settings.model_fields[field].description or field.replace("_", " ")


class StartupError(Exception):
    """A start-up failure: one line for the operator and the exit status."""

    def __init__(self, code: int, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


def _settings_error(exc: ValidationError) -> str:
    parts = []
    for error in exc.errors():
        field = str(error["loc"][0]) if error["loc"] else "?"
        flag = FLAGS[field][0] + ", " if field in FLAGS else ""
        known = field in Settings.model_fields
        where = f"{field} ({flag}PITUNE_{field.upper()})" if known else field
        parts.append(f"{where}: {error['msg']}")
    return "; ".join(parts)


def read_settings(args: argparse.Namespace) -> Settings:
    overrides = {field: getattr(args, field) for field in FLAGS if hasattr(args, field)}
    try:
        return load_settings(args.config, **overrides)
    except ValidationError as exc:
        raise StartupError(
            EXIT_USAGE,
            f"invalid settings: {_settings_error(exc)}. Fix the flag, PITUNE_* variable or "
            "config file entry (see pitune tuner --help)",
        ) from None
    except SettingsError as exc:  # an environment variable that is not valid JSON
        cause = f": {exc.__cause__}" if exc.__cause__ else ""
        message = f"invalid settings: {one_line(exc)}{one_line(cause)}"
        raise StartupError(EXIT_USAGE, message) from None
    except FileNotFoundError as exc:
        raise StartupError(
            EXIT_NO_INPUT, f"{exc}: fix --config or PITUNE_CONFIG, or leave it unset"
        ) from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        # a typo in the file is the operator's to fix: status 2, which a supervisor does not
        # restart on (a restart would fail the same way, forever)
        where = args.config or os.environ.get("PITUNE_CONFIG")
        raise StartupError(
            EXIT_USAGE,
            f"config file {where} is not valid TOML: {one_line(exc)}. Fix the file "
            "(--config or PITUNE_CONFIG)",
        ) from None


def check_files(settings: Settings) -> None:
    weights = settings.agent_weights
    if weights and weights != UNTRAINED and not Path(weights).is_file():
        raise StartupError(
            EXIT_NO_INPUT,
            f"agent weights file not found: {weights}. Fix --agent-weights "
            "(PITUNE_AGENT_WEIGHTS) or leave it unset for the shipped weights",
        )
    if settings.zenoh_config is not None and not settings.zenoh_config.is_file():
        raise StartupError(
            EXIT_NO_INPUT,
            f"Zenoh config file not found: {settings.zenoh_config}. "
            "Fix --zenoh-config (PITUNE_ZENOH_CONFIG)",
        )
    check_archive(settings.history_archive)
    db = settings.db_path
    if not settings.postgres and str(db) != ":memory:" and db.is_dir():
        raise StartupError(
            EXIT_CANT_CREATE,
            f"--db {db} is a directory: give the database file's path, e.g. {db / 'pitune.db'}",
        )


def check_archive(archive: Path | None) -> None:
    """The retention's archive can be appended to: else every pass would fail, and delete
    nothing, for as long as the tuner runs (the store unbounded). A file this check
    creates is removed: a tuner refused later leaves nothing behind."""
    if archive is None:
        return
    existed = archive.exists()
    try:
        with open(archive, "ab"):
            pass
    except OSError as exc:  # its folder missing, a directory, no permission
        raise StartupError(
            EXIT_CANT_CREATE,
            f"cannot append to the history archive {archive}: {exc.strerror}. Fix "
            "history_archive (PITUNE_HISTORY_ARCHIVE: an existing folder), or set it to none",
        ) from None
    if not existed:
        archive.unlink()


class StoreLock:
    """An exclusive ``flock`` on ``<db>.lock``, held while the process lives: a second
    tuner on the same database refuses to start. The kernel drops it when the process
    ends, however it ends (SIGKILL included), so there is no stale lock to clean up."""

    def __init__(self, db: Path, owner: str) -> None:
        self.path = db.with_name(db.name + ".lock")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise StartupError(
                EXIT_CANT_CREATE,
                f"cannot create the store's lock file {self.path}: {exc.strerror}. "
                "Check --db (PITUNE_DB_PATH) and the directory's permissions",
            ) from None
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EACCES):
                raise
            holder = os.pread(self.fd, 200, 0).decode(errors="replace").strip() or "unknown"
            os.close(self.fd)
            raise StartupError(
                EXIT_LOCKED,
                f"another tuner owns the store {db} (lock {self.path} held by {holder}): "
                "stop it first, or give this tuner its own --db",
            ) from None
        os.ftruncate(self.fd, 0)
        os.pwrite(self.fd, f"pid {os.getpid()} instance {owner}\n".encode(), 0)

    def release(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)  # closing the last descriptor releases the flock
            self.fd = -1


def bind_api(settings: Settings) -> socket.socket:
    """The admin API's listening socket, bound now, before the tuner joins the bus."""
    host, port = settings.api_host, settings.api_port
    what = f"--api-host {host} --api-port {port}"
    try:
        family, kind, proto, _, address = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )[0]
    except socket.gaierror as exc:
        raise StartupError(
            EXIT_USAGE, f"cannot resolve the API host {host!r} ({exc.strerror}): fix {what}"
        ) from None
    sock = socket.socket(family, kind, proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(address)
    except OSError as exc:
        sock.close()
        hint = (
            "another process listens there (another tuner?): stop it or pick another "
            "--api-port (PITUNE_API_PORT)"
            if exc.errno == errno.EADDRINUSE
            else "use an address of this host in --api-host (PITUNE_API_HOST)"
        )
        raise StartupError(
            EXIT_UNAVAILABLE, f"cannot listen on {host}:{port} ({exc.strerror}): {hint}"
        ) from None
    sock.set_inheritable(True)
    return sock


def zenoh_failure(exc: Exception, settings: Settings) -> StartupError:
    text = one_line(exc)
    endpoints = f"--listen {','.join(settings.zenoh_listen) or '-'} / --connect " + (
        ",".join(settings.zenoh_connect) or "-"
    )
    if "Address already in use" in text:
        return StartupError(
            EXIT_UNAVAILABLE,
            f"cannot join the Zenoh bus: {text}. Another process (another tuner? a router?) "
            "listens there: stop it or pick another --listen (PITUNE_ZENOH_LISTEN)",
        )
    if "Cannot assign requested address" in text:
        return StartupError(
            EXIT_UNAVAILABLE,
            f"cannot join the Zenoh bus: {text}. Listen on an address of this host "
            "(--listen, PITUNE_ZENOH_LISTEN)",
        )
    usage, message = join_failure(exc, endpoints)
    return StartupError(EXIT_USAGE if usage else EXIT_UNAVAILABLE, message)


def start_tuner(settings: Settings):
    """The tuner, started (agent loaded, store open, on the bus)."""
    import psycopg
    import torch  # heavy: only once the cheap checks passed
    import zenoh

    from service.daemon.migrations import SchemaTooNew
    from service.daemon.store import EpochAheadError
    from service.daemon.store_pg import redacted
    from service.daemon.tuner import Tuner

    torch.set_num_threads(settings.inference_threads)
    try:
        tuner = Tuner(settings)
    except Exception as exc:
        raise StartupError(
            EXIT_NO_INPUT,
            f"cannot load the agent weights {settings.agent_weights or '(shipped)'}: "
            f"{one_line(exc)}. Fix --agent-weights (PITUNE_AGENT_WEIGHTS)",
        ) from exc
    try:
        tuner.start()
    except zenoh.ZError as exc:
        raise zenoh_failure(exc, settings) from exc
    except EpochAheadError as exc:
        raise StartupError(EXIT_USAGE, str(exc)) from exc
    except (psycopg.Error, SchemaTooNew) as exc:
        location = redacted(settings.db_path) if settings.postgres else settings.db_path
        raise StartupError(
            EXIT_CANT_CREATE,
            f"cannot open the store {location}: {one_line(exc)}. Check --db "
            "(PITUNE_DB_PATH): a reachable PostgreSQL server and database, a user allowed "
            "to create tables there, and a pitune at least as new as the one that wrote it",
        ) from exc
    except (sqlite3.Error, OSError) as exc:
        raise StartupError(
            EXIT_CANT_CREATE,
            f"cannot open the store {settings.db_path}: {one_line(exc)}. Check --db "
            "(PITUNE_DB_PATH): a writable SQLite file, or a new path",
        ) from exc
    return tuner


def other_tuners(tuner, settings: Settings) -> list[str]:
    """Liveliness tokens of other tuners on this key prefix (this tuner's excluded)."""
    keys = settings.keys
    replies = tuner.bus.session.liveliness().get(keys.all_tuners, timeout=1.0)
    found = {str(reply.ok.key_expr) for reply in replies if reply.ok is not None}
    return sorted(found - {keys.tuner(settings.instance_id)})


def check_alone_on_prefix(tuner, settings: Settings, wait_s: float = PREFIX_LEASE_S) -> None:
    """Refuse to run beside another tuner with the same key prefix on the bus: both
    would tune the same loops. A token still there after ``wait_s`` is a live tuner."""
    deadline = time.monotonic() + wait_s
    others = other_tuners(tuner, settings)
    if others:
        log.warning(
            "another tuner is on the bus with key prefix %r: %s; waiting up to %.0f s for "
            "its token to go (a tuner stopped moments ago)",
            settings.key_prefix,
            ", ".join(others),
            wait_s,
        )
    while others and time.monotonic() < deadline:
        time.sleep(1.0)
        others = other_tuners(tuner, settings)
    if others:
        raise StartupError(
            EXIT_LOCKED,
            f"another tuner runs on the bus with key prefix {settings.key_prefix!r} "
            f"({', '.join(others)}): both would tune the same loops. Stop it, or give this "
            "tuner its own --prefix (PITUNE_KEY_PREFIX)",
        )


def run(args: argparse.Namespace) -> int:
    configured = False
    try:
        settings = read_settings(args)
        logs.configure(settings.log_level, settings.log_format)
        configured = True
        for message in unknown_variables():
            log.warning("%s", message)
        return serve(settings)
    except StartupError as exc:
        if configured:
            log.critical("cannot start: %s", exc.message, exc_info=log.isEnabledFor(logging.DEBUG))
            logging.shutdown()
        else:
            print(f"pitune tuner: cannot start: {exc.message}", file=sys.stderr)
        return exc.code
    except KeyboardInterrupt:
        return 130
    except Exception:  # a bug: its traceback, in the log's format when there is one
        if not configured:
            raise
        log.critical("unexpected failure", exc_info=True)
        logging.shutdown()
        return EXIT_FAILED


def serve(settings: Settings) -> int:
    check_files(settings)
    if (mismatch := lease_mismatch(settings)) is not None:
        raise StartupError(EXIT_USAGE, mismatch)
    # a PostgreSQL store is shared by a cluster: its leases (service.daemon.cluster) keep
    # two members off the same loops, where an SQLite file has one owner
    lock = (
        None
        if settings.postgres or str(settings.db_path) == ":memory:"
        else StoreLock(settings.db_path, settings.instance_id)
    )
    sock = bind_api(settings)

    def on_sigterm(*_: object) -> None:
        sys.exit(EXIT_OK)  # also during start-up: a stop asked for, the finally cleans up

    # uvicorn shuts down gracefully on SIGTERM and SIGINT, then re-raises the signal with
    # the handler it found installed; make that a clean exit so supervisors see status 0,
    # not -15 (or a KeyboardInterrupt traceback for Ctrl-C).
    signal.signal(signal.SIGTERM, on_sigterm)
    signal.signal(signal.SIGINT, on_sigterm)
    tuner = None
    try:
        tuner = start_tuner(settings)
        if not settings.postgres:  # cluster members share the prefix by design
            check_alone_on_prefix(tuner, settings)
        from service.daemon.api import create_app

        server = uvicorn.Server(
            uvicorn.Config(
                create_app(settings, tuner=tuner),
                log_config=None,  # uvicorn's lines go through our handler and format
                log_level=settings.log_level,
                lifespan="on",
                # (uvicorn's default believes any client on 127.0.0.1: a local process set
                # the address the audit records)
                forwarded_allow_ips=settings.api_trusted_proxies,
            )
        )
        log.info("admin API on http://%s:%d", settings.api_host, sock.getsockname()[1])
        server.run(sockets=[sock])
        return EXIT_OK if server.started else EXIT_FAILED
    finally:
        if tuner is not None and tuner.store is not None:  # the lifespan did not stop it
            tuner.stop()
        sock.close()
        if lock is not None:
            lock.release()
