"""The real PostgreSQL server of the tests (:class:`service.bench.pgserver.PgServer`),
as fixtures (registered by tests/conftest.py): ``pg_server`` for the session and
``pg_url``, a fresh empty database per test.

Missing server binaries FAIL the tests that need them, saying what to install (Debian's
``postgresql`` package, as the README's test set-up says): a silently skipped test
would hide an untested backend.
"""

from __future__ import annotations

import pytest

from service.bench.pgserver import PgServer, PgUnavailable


@pytest.fixture(scope="session")
def pg_server():
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
