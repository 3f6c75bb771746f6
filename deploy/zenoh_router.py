#!/usr/bin/env python3
"""A Zenoh router from a JSON5 config file: a stand-in for ``zenohd`` where its image
cannot be pulled (an air-gapped host, tests).

    python deploy/zenoh_router.py --config deploy/zenoh/router.json5 \
        [--set transport/auth/usrpwd/dictionary_file='"/path/credentials.txt"']

It opens one Zenoh session in router mode from the file, exactly as ``zenohd --config``
reads it (listen endpoints, user/password authentication, access control), with the
same Rust core as the ``eclipse/zenoh`` image of the same version (the Python binding
``eclipse-zenoh`` of the pitune image, 1.10.x). It prints one line once listening and
runs until SIGTERM or SIGINT. ``deploy/docker-compose.pyrouter.yml`` runs it in the
pitune image instead of ``eclipse/zenoh``; ``deploy/smoke.sh --python-router`` uses it.
Not a replacement for ``zenohd`` in production: no plugins, no admin space REST API.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading

import zenoh


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", required=True, help="Zenoh JSON5 config (router.json5)")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="PATH=JSON5",
        help="override one setting, e.g. listen/endpoints='[\"tcp/127.0.0.1:7448\"]'",
    )
    args = parser.parse_args(argv)
    try:
        config = zenoh.Config.from_file(args.config)
        for item in args.set:
            path, sep, value = item.partition("=")
            if not sep:
                parser.error(f"--set {item!r}: expected PATH=JSON5")
            config.insert_json5(path, value)
        if json.loads(config.get_json("mode")) != "router":
            config.insert_json5("mode", '"router"')
        session = zenoh.open(config)
    except zenoh.ZError as exc:
        print(f"zenoh router: cannot start from {args.config}: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    endpoints = json.loads(config.get_json("listen/endpoints"))
    acl = json.loads(config.get_json("access_control/enabled"))
    print(
        f"zenoh router {session.zid()} listening on {', '.join(endpoints)}, "
        f"access control {'on' if acl else 'OFF'}",
        flush=True,
    )
    try:
        while not stop.wait(1.0):
            pass
    finally:
        session.close()
    print("zenoh router stopped", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
