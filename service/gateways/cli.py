"""``pitune gateway``: gateways between a control system and the pitune bus.

* ``pitune gateway opcua --map site.toml``: the OPC UA gateway (``docs/opcua.md``);
  ``--check`` connects once, prints every loop's values and gains, and exits.
* ``pitune gateway certs --out DIR``: a self-signed client certificate and key for it.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="gateway_command", metavar="KIND", required=True)
    op = sub.add_parser("opcua", help="OPC UA gateway: PID blocks <-> the pitune bus")
    op.add_argument("--map", type=Path, required=True, help="the site's map file (TOML)")
    op.add_argument("--check", action="store_true",
                    help="connect, print each loop's values and gains, exit")  # fmt: skip
    op.add_argument("--log-level", default="warning",
                    choices=("debug", "info", "warning", "error"))  # fmt: skip
    op.add_argument("--status-interval", type=float, default=60.0,
                    help="status line every N s (60)")  # fmt: skip
    op.add_argument("--report", type=Path, default=None, metavar="JSON",
                    help="write counters and write latencies here at exit")  # fmt: skip
    certs = sub.add_parser("certs", help="generate a self-signed OPC UA certificate and key")
    certs.add_argument("--out", type=Path, required=True, help="folder for the files")
    certs.add_argument("--name", default="gateway", help="file stem: NAME-cert.der, NAME-key.pem")
    certs.add_argument("--uri", default="urn:pitune:gateway",
                       help="application URI (the map's server.application_uri)")  # fmt: skip
    certs.add_argument("--host", action="append", default=None,
                       help="DNS name(s) in the certificate (default: this host)")  # fmt: skip
    certs.add_argument("--days", type=_days, default=730, help="validity, days (730)")
    certs.add_argument("--server", action="store_true", help="a server certificate instead")
    certs.add_argument("--force", action="store_true",
                       help="replace an existing pair (the server trusts the old one)")  # fmt: skip


def _days(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"at least 1 day, not {value}")
    return value


def run(args: argparse.Namespace) -> int:
    if args.gateway_command == "certs":
        from service.gateways.opcua.certs import generate_pair

        cert, key = args.out / f"{args.name}-cert.der", args.out / f"{args.name}-key.pem"
        try:
            generate_pair(cert, key, application_uri=args.uri, hosts=args.host,
                          days=args.days, server=args.server, replace=args.force)  # fmt: skip
        except OSError as exc:  # FileExistsError among them
            print(f"pitune gateway certs: {exc}", file=sys.stderr)
            return 2
        print(f"wrote {cert} and {key} (mode 0600); trust {cert.name} on the OPC UA server")
        return 0
    import faulthandler

    faulthandler.register(signal.SIGUSR1)  # kill -USR1 <pid>: every thread's stack on stderr
    logging.basicConfig(
        level=getattr(logging, args.log_level.upper()),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    logging.getLogger("asyncua").setLevel(logging.ERROR)
    from service.gateways.opcua.sitemap import MapError, load_map

    try:
        site = load_map(args.map)
        if site.server.user is not None:
            site.server.password()
    except MapError as exc:
        print(f"pitune gateway opcua: {exc}", file=sys.stderr)
        return 2
    if args.check:
        return asyncio.run(check(site))
    return asyncio.run(serve(site, args.status_interval, args.report))


async def serve(site, status_interval: float, report: Path | None = None) -> int:
    import zenoh

    from service.gateways.opcua.bridge import OpcUaGateway
    from service.gateways.registration import RegistrationError
    from service.wire.session import join_failure, session_config

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    bus = site.bus
    try:
        session = zenoh.open(
            session_config(
                config_file=bus.zenoh_config,
                mode=bus.mode,
                connect=bus.connect or None,
                listen=bus.listen or None,
            )
        )
    except zenoh.ZError as exc:  # the map's [bus] is wrong (2), or a port in use (1)
        usage, message = join_failure(exc, "the map's [bus] section")
        print(f"pitune gateway opcua: {message}", file=sys.stderr)
        return 2 if usage else 1
    try:
        gateway = OpcUaGateway(site, session, status_interval_s=status_interval)
        print(f"gateway: {len(site.loops)} loops from {site.server.url} "
              f"({site.server.security.value}) on the bus", flush=True)  # fmt: skip
        try:
            await gateway.run(stop)
        except RegistrationError as exc:
            print(f"pitune gateway opcua: {exc}", file=sys.stderr)
            return 1
        finally:
            print(f"gateway stopped: {gateway.status_line()}; {dict(gateway.stats)}", flush=True)
            if report is not None:
                import json

                report.write_text(json.dumps(gateway.report(), indent=2) + "\n")
    finally:
        session.close()
    return 0


async def check(site) -> int:
    """Connect once and print what the gateway would see."""
    from service.gateways.opcua.client import Item, OpcUaLink
    from service.gateways.opcua.loops import LoopRuntime

    link = OpcUaLink(site.server)
    loops = [LoopRuntime(k, cfg) for k, cfg in enumerate(site.loops)]
    nodes = [(Item(lr.index, f), n) for lr in loops for f, n in lr.cfg.nodes().items()]
    try:
        ones = {lr.index: 1 for lr in loops}
        changes = await link.open(
            nodes, sampling_ms={k: 1000.0 for k in ones}, queue_size=ones, publishing_ms=1000.0
        )
    except Exception as exc:
        print(f"cannot connect to {site.server.url}: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
    try:
        bad = 0
        for ch in changes:
            lr = loops[ch.item.loop]
            if ch.good:
                lr.values[ch.item.field] = ch.value
            else:
                bad += 1
                print(f"{lr.cfg.id}.{ch.item.field}: unreadable", file=sys.stderr)
        for lr in loops:
            gains = lr.in_force()
            kp_ki = "unreadable" if gains is None else f"kp={gains[0]:.5g} ki={gains[1]:.5g}/s"
            print(f"{lr.cfg.id}: sp={lr.values.get('sp')} pv={lr.values.get('pv')} "
                  f"auto={lr.auto} tuning_enable={lr.enabled} saturated={lr.saturated} "
                  f"P={lr.values.get('p')} I={lr.values.get('i')} ({lr.cfg.form.describe()}) "
                  f"-> {kp_ki}")  # fmt: skip
        return 1 if bad else 0
    finally:
        await link.close()
