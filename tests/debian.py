"""System packages the tests need, installed from Debian's repositories when missing:
the one rule of the README's test set-up (``python -m pytest`` installs what it needs
when it runs as root with apt-get, and otherwise says what to install)."""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from pathlib import Path

APT_TIMEOUT_S = 600
LOCK = Path(tempfile.gettempdir()) / "pitune-tests-apt.lock"
"""Held while installing: the suite's workers (pytest-xdist) may need packages at once,
and a second apt-get would fail on dpkg's lock instead of waiting for it."""


def apt_install(package: str, present: Callable[[], bool]) -> str | None:
    """Install ``package`` unless ``present()``; None once it is there, else why not."""
    if present():
        return None
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        return f"{package} missing and not root with apt-get: apt-get install -y {package}"
    with LOCK.open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        return _install(package, present)


def _install(package: str, present: Callable[[], bool]) -> str | None:
    """apt-get install ``package`` (under :data:`LOCK`); None once it is there."""
    if present():  # another worker installed it while this one waited
        return None
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    install = ["apt-get", "install", "-y", "--no-install-recommends", package]
    try:
        for argv in (install, ["apt-get", "update"], install):  # stale lists: update, again
            done = subprocess.run(argv, env=env, capture_output=True, text=True,
                                  timeout=APT_TIMEOUT_S, check=False)  # fmt: skip
            if argv is install and done.returncode == 0:
                break
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"apt-get install {package} failed: {exc}"
    if done.returncode != 0 or not present():
        tail = (done.stderr or done.stdout).strip().splitlines()[-1:]
        return f"apt-get install {package} failed ({done.returncode}): {' '.join(tail)}"
    return None
