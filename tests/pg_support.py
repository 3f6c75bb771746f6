"""The real PostgreSQL server of the tests (:class:`service.bench.pgserver.PgServer`),
as fixtures (registered by tests/conftest.py): ``pg_server`` for the session and
``pg_url``, a fresh empty database per test.

Missing server binaries are installed from Debian's ``postgresql`` package when the
tests run as root (:func:`tests.debian.apt_install`); otherwise they FAIL the tests that
need them, saying what to install: a silently skipped test would hide an untested
backend.
"""

from __future__ import annotations

import pytest

from service.bench.pgserver import PgServer, PgUnavailable, pg_bin
from tests.debian import apt_install


@pytest.fixture(scope="session")
def pg_server():
    why = apt_install("postgresql", lambda: pg_bin() is not None)
    if why is not None:
        pytest.fail(f"no PostgreSQL server binaries: {why}")
    try:
        server = PgServer()
    except PgUnavailable as exc:
        pytest.fail(str(exc))
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture
def pg_url(pg_server: PgServer) -> str:
    return pg_server.create_database()
