"""Fixtures of the console's browser tests: Debian's Chromium driven by Playwright for
Python, and the daemon served in-process (see :mod:`service.daemon.console.screenshots`).

Chromium comes from the Debian packages (``apt-get install -y chromium``; Playwright's
own browser download does not work on these machines): the ``chromium`` fixture
installs it when it is missing and the tests run as root, and otherwise skips the
browser tests saying why. Playwright itself is the test extra ``playwright``.

Import the fixtures into a test module with ``from tests.browser import *``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.daemon.console.screenshots import CHROMIUM, CHROMIUM_ARGS, Daemon, serve
from tests.tuner_support import tuner_settings

__all__ = ["chromium", "browser", "daemon", "new_page", "TOKEN"]

TOKEN = "console-test-token"
APT_TIMEOUT_S = 600


def _install_chromium() -> str | None:
    """Why Chromium is not there (None: it is, now)."""
    if Path(CHROMIUM).exists():
        return None
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        return f"{CHROMIUM} missing and not root with apt-get: apt-get install -y chromium"
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    try:
        done = subprocess.run(
            ["apt-get", "install", "-y", "--no-install-recommends", "chromium"],
            env=env, capture_output=True, text=True, timeout=APT_TIMEOUT_S, check=False,
        )  # fmt: skip
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"apt-get install chromium failed: {exc}"
    if done.returncode != 0 or not Path(CHROMIUM).exists():
        tail = (done.stderr or done.stdout).strip().splitlines()[-1:]
        return f"apt-get install chromium failed ({done.returncode}): {' '.join(tail)}"
    return None


@pytest.fixture(scope="session")
def chromium() -> str:
    """Path of Debian's Chromium, installed if missing (root); skip if impossible."""
    pytest.importorskip("playwright", reason="Playwright for Python: pip install -e '.[test]'")
    why = _install_chromium()
    if why is not None:
        pytest.skip(f"no headless Chromium: {why}")
    return CHROMIUM


@pytest.fixture(scope="module")
def browser(chromium: str) -> Iterator[object]:
    """One Chromium per test module (Playwright's sync API runs its own event loop: it is
    closed before other modules' asyncio tests run)."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


@pytest.fixture
def new_page(browser) -> Iterator[object]:
    """``new_page(csp=False)``: a page in a fresh context (own cookies). CSP is bypassed
    by default because Playwright's ``wait_for_function`` evaluates strings, which the
    console's CSP forbids; ``csp=True`` keeps it (to check the pages obey it)."""
    contexts = []

    def make(csp: bool = False):
        context = browser.new_context(viewport={"width": 1400, "height": 900}, bypass_csp=not csp)
        context.set_default_timeout(15_000)
        contexts.append(context)
        return context.new_page()

    yield make
    for context in contexts:
        context.close()


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[Daemon]:
    """The tuner daemon with the console on a free port (token set, untrained agent)."""
    with serve(tuner_settings(tmp_path, api_token=TOKEN)) as d:
        yield d
