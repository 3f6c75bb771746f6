"""``pitune demo``: the tuner and a simulated two-tank plant, end to end, on loopback.

Starts the tuner daemon (admin API and Zenoh peer on free loopback ports, SQLite in a
work folder) and the plant simulator as separate processes; the plant registers the
two-tank level loop with the paper's crude model 1.2/(30 s + 1) and runs a fixed
simulated span at a high speed factor while a progress line shows the simulated time,
the gains in force and the recent tracking error. Both processes are then stopped and
``demo/`` receives:

* ``two_tank.png``: level vs setpoint vs target, tuned and untuned, and kp, ki over time;
* ``summary.md`` and ``summary.json``: the tracking MSE (level vs target trajectory
  over the last two setpoint changes) of the tuned run and of the untuned baseline;
* ``tank1.csv``: the tuned run's trajectory log.

The untuned baseline is the same plant, schedule and seed simulated in-process with
the registered gains held fixed (:func:`plant_sim.process.untuned_baseline`).

:class:`Child` and :func:`free_port` are the process plumbing the end-to-end tests
share with the demo.
"""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
LOOP_ID = "tank1"


class DemoError(RuntimeError):
    """A part of the demo failed; the message says which and why."""


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def pitune(*args: str) -> list[str]:
    """argv running a ``pitune`` sub-command with this interpreter, from any install."""
    return [sys.executable, "-m", "service.cli", *args]


class Child:
    """A ``pitune`` subprocess with its output in a log file; reaped by :meth:`stop`."""

    def __init__(self, name: str, argv: list[str], *, env: dict[str, str], log: Path) -> None:
        self.name = name
        self.log = log
        log.parent.mkdir(parents=True, exist_ok=True)
        with log.open("ab") as out:
            self.proc = subprocess.Popen(
                argv, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT
            )

    @property
    def running(self) -> bool:
        return self.proc.poll() is None

    def tail(self, lines: int = 15) -> str:
        text = self.log.read_text(errors="replace") if self.log.exists() else ""
        return "\n".join(text.splitlines()[-lines:])

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

    def wait(self, timeout: float) -> int:
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            raise DemoError(
                f"{self.name} still running after {timeout:g} s:\n{self.tail()}"
            ) from None

    def failed(self) -> DemoError:
        return DemoError(f"{self.name} exited with code {self.proc.returncode}:\n{self.tail()}")


def wait_healthy(api: str, child: Child, timeout: float = 90.0) -> None:
    """Until ``GET /healthz`` answers 200; fail early if ``child`` dies."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if not child.running:
            raise child.failed()
        with contextlib.suppress(httpx.HTTPError):
            if httpx.get(f"{api}/healthz", timeout=2.0).status_code == 200:
                return
        time.sleep(0.2)
    raise DemoError(f"{child.name} not healthy after {timeout:g} s:\n{child.tail()}")
