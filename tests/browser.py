"""Fixtures of the console's browser tests: Debian's Chromium driven by Playwright for
Python, and the daemon served in-process (see :mod:`service.daemon.console.screenshots`).

Chromium comes from the Debian packages (``apt-get install -y chromium``; Playwright's
own browser download does not work on these machines): the ``chromium`` fixture
installs it when it is missing and the tests run as root, and otherwise skips the
browser tests saying why. Playwright itself is the test extra ``playwright``.

Import the fixtures into a test module with ``from tests.browser import *``.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from service.daemon.console.screenshots import CHROMIUM, CHROMIUM_ARGS, Daemon, serve
from tests.debian import apt_install
from tests.tuner_support import tuner_settings

__all__ = ["chromium", "browser", "daemon", "new_page", "TOKEN"]

TOKEN = "console-test-token"


@pytest.fixture(scope="session")
def chromium() -> str:
    """Path of Debian's Chromium, installed if missing (root); skip if impossible."""
    pytest.importorskip("playwright", reason="Playwright for Python: pip install -e '.[test]'")
    why = apt_install("chromium", Path(CHROMIUM).exists)
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
