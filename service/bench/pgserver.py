"""A throwaway PostgreSQL server: ``initdb`` into a temporary directory and ``pg_ctl
start`` on a free loopback port (its unix socket in that directory), for the tests and
for ``pitune bench --instances N`` without a ``--postgres`` URL.

The server binaries come from Debian's ``postgresql`` package (``apt-get install
postgresql``: ``/usr/lib/postgresql/<version>/bin``) or the PATH. ``initdb`` refuses to
run as root (CI containers), so as root the server runs as the ``postgres`` user (the
package creates it) or ``nobody``. fsync is off: a benchmark's or a test's database.
"""

from __future__ import annotations

import glob
import itertools
import os
import pwd
import shutil
import subprocess
import tempfile
from pathlib import Path

import psycopg

from service.wire.session import free_port


class PgUnavailable(RuntimeError):
    """No PostgreSQL server binaries, or no user to run them as."""


_names = itertools.count()


def pg_bin() -> Path | None:
    """The directory of ``initdb`` and ``pg_ctl`` (the PATH first, then Debian's)."""
    found = shutil.which("initdb")
    if found:
        return Path(os.path.realpath(found)).parent
    versions = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), reverse=True)
    return Path(versions[0]).parent if versions else None


def _as_user() -> list[str]:
    """The command prefix that runs the server as a non-root user, when we are root."""
    if os.geteuid() != 0:
        return []
    for user in ("postgres", "nobody"):
        try:
            pwd.getpwnam(user)
        except KeyError:
            continue
        return ["runuser", "-u", user, "--"]
    raise PgUnavailable("running as root without a 'postgres' or 'nobody' user for initdb")


class PgServer:
    def __init__(self) -> None:
        bindir = pg_bin()
        if bindir is None:
            raise PgUnavailable(
                "PostgreSQL server binaries not found (initdb, pg_ctl): install Debian's "
                "'postgresql' package (apt-get install postgresql) as the README's test "
                "set-up says"
            )
        self.dir = Path(tempfile.mkdtemp(prefix="pitune-pg-"))
        self.port = free_port()
        prefix = _as_user()
        if prefix:
            user = prefix[2]
            os.chown(self.dir, pwd.getpwnam(user).pw_uid, pwd.getpwnam(user).pw_gid)
        data = self.dir / "data"
        subprocess.run(
            [*prefix, str(bindir / "initdb"), "-D", str(data), "-U", "pitune",
             "--auth=trust", "-E", "UTF8", "--no-sync", "--locale=C"],
            check=True, capture_output=True,
        )  # fmt: skip
        self._ctl = [*prefix, str(bindir / "pg_ctl"), "-D", str(data)]
        self.resume()
        self.admin = self.url("postgres")

    def resume(self) -> None:
        """Start the server (again, after :meth:`halt`), on the same port and data."""
        options = f"-p {self.port} -k {self.dir} -c listen_addresses=127.0.0.1 -c fsync=off"
        subprocess.run(
            [*self._ctl, "-o", options, "-l", str(self.dir / "log"), "-w", "start"],
            check=True, capture_output=True,
        )  # fmt: skip

    def halt(self) -> None:
        """Stop the server as an administrator restarting it would (``pg_ctl -m fast``:
        its sessions are told and closed), keeping its data for :meth:`resume`."""
        subprocess.run([*self._ctl, "-m", "fast", "-w", "stop"], check=True, capture_output=True)

    @property
    def pid(self) -> int:
        """The postmaster's process id (its backends are its children)."""
        return int((self.dir / "data" / "postmaster.pid").read_text().split()[0])

    def url(self, database: str) -> str:
        return f"postgresql://pitune@127.0.0.1:{self.port}/{database}"

    def create_database(self) -> str:
        name = f"t{os.getpid()}_{next(_names)}"
        with psycopg.connect(self.admin, autocommit=True) as conn:
            conn.execute(f"CREATE DATABASE {name}")
        return self.url(name)

    def stop(self) -> None:
        subprocess.run([*self._ctl, "-m", "immediate", "stop"], capture_output=True)
        shutil.rmtree(self.dir, ignore_errors=True)
