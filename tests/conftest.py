"""Fixtures shared by the test modules: a real PostgreSQL server (tests/pg_support.py)."""

from tests.pg_support import pg_server, pg_url  # noqa: F401
