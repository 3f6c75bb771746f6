"""Processes of pitune run by pitune: the demo, the load benchmark and the tests share this.

:class:`Proc` is one subprocess with its output in a log file: it is waited for on a
readiness signal (any predicate, e.g. :func:`http_ok` on ``/readyz``), stopped with
SIGTERM then SIGKILL, and reports its exit status and the tail of its log when it fails.
:class:`TunerProcess` is a ``pitune tuner`` on free loopback ports that can be killed and
restarted on the same database and ports; :class:`Stack` adds plant simulators
(``pitune plant run``) in one work folder, as the demo and the end-to-end tests run them.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import httpx

from service.daemon.settings import UNTRAINED
from service.wire.session import free_port

ROOT = Path(__file__).resolve().parents[1]
STORE_NAME = "pitune.db"
"""The tuner's database in a :class:`Stack`'s work folder."""


class ProcError(RuntimeError):
    """A process failed or did not get ready; the message says which and shows its log."""


def pitune(*args: str) -> list[str]:
    """argv running a ``pitune`` sub-command with this interpreter, from any install."""
    return [sys.executable, "-m", "service.cli", *args]


def user_path(text: str) -> Path:
    """An argparse type for a path handed to a child process: made absolute against the
    caller's folder, for the children run in the checkout (ROOT), where a relative path
    names another file."""
    return Path(text).expanduser().absolute()


def weights_path(text: str) -> str:
    """An argparse type for ``--agent-weights`` handed to a child tuner: a file (made
    absolute, :func:`user_path`) or ``untrained``."""
    return text if text == UNTRAINED else str(user_path(text))


def clean_env(**extra: str) -> dict[str, str]:
    """This environment without the caller's PITUNE_* variables (a stray token or config
    file must not leak into a child), the checkout importable, plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PITUNE_")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    return {**env, **extra}


def http_ok(url: str) -> Callable[[], bool]:
    """Readiness signal: ``GET url`` answers 200."""

    def ready() -> bool:
        with contextlib.suppress(httpx.HTTPError):
            return httpx.get(url, timeout=2.0).status_code == 200
        return False

    return ready


class Proc:
    """A subprocess whose output goes to ``log`` (appended: restarts share one log)."""

    def __init__(
        self,
        name: str,
        argv: list[str],
        *,
        log: Path,
        env: dict[str, str] | None = None,
        cpus: set[int] | None = None,
    ) -> None:
        """Start ``argv`` in the checkout (``env``: :func:`clean_env` by default), pinned
        to ``cpus`` from its first instruction if given."""
        self.name = name
        self.log = log
        log.parent.mkdir(parents=True, exist_ok=True)
        pin = (lambda: os.sched_setaffinity(0, cpus)) if cpus else None
        with log.open("ab") as out:
            self.proc = subprocess.Popen(
                argv, cwd=ROOT, env=clean_env() if env is None else env, stdout=out,
                stderr=subprocess.STDOUT, preexec_fn=pin,
            )  # fmt: skip

    @property
    def pid(self) -> int:
        return self.proc.pid

    @property
    def running(self) -> bool:
        return self.proc.poll() is None

    @property
    def returncode(self) -> int | None:
        return self.proc.poll()

    def tail(self, lines: int = 15) -> str:
        text = self.log.read_text(errors="replace") if self.log.exists() else ""
        return "\n".join(text.splitlines()[-lines:])

    def failed(self) -> ProcError:
        return ProcError(f"{self.name} exited with code {self.proc.returncode}:\n{self.tail()}")

    def wait_ready(self, ready: Callable[[], object], timeout: float = 90.0) -> None:
        """Poll ``ready`` until truthy; fail early, with the log, if the process exits."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if not self.running:
                raise self.failed()
            if ready():
                return
            time.sleep(0.1)
        raise ProcError(f"{self.name} not ready after {timeout:g} s:\n{self.tail()}")

    def wait(self, timeout: float) -> int:
        """The exit code once the process ends by itself within ``timeout``."""
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise ProcError(
                f"{self.name} still running after {timeout:g} s:\n{self.tail()}"
            ) from None

    def signal(self, sig: int, timeout: float = 30.0) -> int:
        """Send ``sig``; the exit code once the process ends."""
        if self.running:
            self.proc.send_signal(sig)
        return self.wait(timeout)

    def stop(self, timeout: float = 20.0) -> int:
        """SIGTERM, then SIGKILL after ``timeout``; the exit code."""
        if self.running:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            return self.kill()

    def kill(self) -> int:
        """SIGKILL, as a crash would."""
        if self.running:
            self.proc.kill()
        return self.proc.wait()

    def cpu_seconds(self) -> float:
        """User + system CPU time so far (``/proc``)."""
        fields = Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def rss_mb(self) -> float:
        """Resident set size now (``/proc``)."""
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
        return float("nan")


class TunerProcess:
    """``pitune tuner`` with its database ``db`` on free loopback ports (the admin API and
    a Zenoh listener); every :meth:`start` reuses them, so a restart resumes the state."""

    def __init__(
        self,
        db: Path,
        *args: str,
        log: Path,
        token: str | None = None,
        env: dict[str, str] | None = None,
        cpus: set[int] | None = None,
    ) -> None:
        """``args`` are added to the tuner's command line, ``env`` to its environment."""
        self.db = db
        self.cpus = cpus
        self.log = log
        self.token = token
        self.api = f"http://127.0.0.1:{free_port()}"
        self.zenoh = f"tcp/127.0.0.1:{free_port()}"
        self.args = args
        self.env = env or {}
        self.proc: Proc | None = None

    def start(self, *extra: str, timeout: float = 90.0) -> Proc:
        """Start it and wait until ``/readyz`` answers (worker, bus and store up)."""
        argv = pitune("tuner", "--api-port", self.api.rsplit(":", 1)[1], "--listen", self.zenoh,
                      "--db", str(self.db), *self.args, *extra)  # fmt: skip
        token = {"PITUNE_API_TOKEN": self.token} if self.token else {}
        env = clean_env(**token, **self.env)
        self.proc = Proc("tuner", argv, log=self.log, env=env, cpus=self.cpus)
        self.proc.wait_ready(http_ok(f"{self.api}/readyz"), timeout)
        return self.proc

    def http(self) -> httpx.Client:
        """A client of the admin API, with the token if there is one."""
        headers = {"Authorization": f"Bearer {self.token}"} if self.token else {}
        return httpx.Client(base_url=self.api, headers=headers, timeout=10.0)

    def stop(self) -> int | None:
        return None if self.proc is None else self.proc.stop()


class Stack:
    """A tuner and plant simulators as separate processes on loopback, sharing a work
    folder (SQLite database, process logs, trajectory logs in ``log/``). The demo runs
    one; the end-to-end tests kill and restart its parts. Leaving it stops them all."""

    def __init__(self, workdir: Path, *, speed: float, agent_weights: str | None = None) -> None:
        self.workdir = workdir
        self.speed = speed
        self.token = secrets.token_urlsafe(16)
        extra = ("--agent-weights", agent_weights) if agent_weights else ()
        # Samples arrive `speed` times faster than the plant's 1 s scan.
        rate = f"{max(50.0, 4.0 * speed):g}"
        self.tuner = TunerProcess(workdir / STORE_NAME, "--max-sample-rate", rate,
                                  "--log-level", "warning", *extra, log=workdir / "tuner.log",
                                  token=self.token)  # fmt: skip
        self.api, self.zenoh = self.tuner.api, self.tuner.zenoh
        self.plants: list[Proc] = []

    @property
    def log_dir(self) -> Path:
        return self.workdir / "log"

    def start_tuner(self, *extra: str) -> Proc:
        """Start the tuner (same database and ports on every restart); wait until ready."""
        return self.tuner.start(*extra)

    def start_plant(self, *plant_args: str) -> Proc:
        """Start a plant simulator that registers its loops and logs their trajectories."""
        # listening on loopback only, as the tuner: a Zenoh peer's default listener is
        # every interface, where any host could read the loop and send it gains
        argv = pitune("plant", "run", *plant_args, "--speed", f"{self.speed:g}",
                      "--connect", self.zenoh, "--listen", "tcp/127.0.0.1:0",
                      "--register", self.api,
                      "--log-dir", str(self.log_dir), "--progress", "0")  # fmt: skip
        log = self.workdir / f"plant{len(self.plants) or ''}.log"
        plant = Proc("plant", argv, log=log, env=clean_env(PITUNE_API_TOKEN=self.token))
        self.plants.append(plant)
        return plant

    def close(self) -> None:
        """Stop every process still running, plants first so none outlives its tuner."""
        for plant in self.plants:
            plant.stop()
        self.tuner.stop()

    def __enter__(self) -> Stack:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
