"""The listening TCP sockets of a process, from /proc (Linux): what a test checks where a
process must not be reachable from other hosts."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path


def listening(pid: int) -> list[str]:
    """The local addresses (hex, as in /proc/net/tcp*) of the process's listening TCP
    sockets."""
    fds = Path(f"/proc/{pid}/fd")
    inodes = set()
    for fd in fds.iterdir():
        with contextlib.suppress(OSError):
            target = os.readlink(fd)
            if target.startswith("socket:["):
                inodes.add(target[8:-1])
    out = []
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A" and fields[9] in inodes:  # LISTEN
                out.append(fields[1].rsplit(":", 1)[0])
    return out


LOOPBACK = {"0100007F", "00000000000000000000000001000000"}
"""127.0.0.1 and ::1 as /proc/net/tcp and tcp6 write them."""
