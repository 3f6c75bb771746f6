"""The command line of ``pitune plant opcua`` (:mod:`plant_sim.opcua_dcs`): the loops,
the server's security, the map it writes for a gateway, and the scan clock."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import time
from pathlib import Path

import numpy as np

from plant_sim.opcua_dcs import DcsSecurity, SimulatedDcs
from plant_sim.scenario import SimulatedLoop
from plant_sim.trajectory import TrajectoryWriter


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``pitune plant opcua``: the loops and simulation as for ``plant run``."""
    from plant_sim.process import add_loop_arguments

    add_loop_arguments(parser)
    parser.add_argument("--many-foptd", type=int, default=0, metavar="N",
                        help="also N FOPTD loops F0000.. (load tests)")  # fmt: skip
    srv = parser.add_argument_group("OPC UA server")
    srv.add_argument("--host", default="127.0.0.1", help="endpoint host (0.0.0.0 in a container)")
    srv.add_argument("--port", type=int, default=4840)
    srv.add_argument("--certificate", type=Path, default=None, help="server certificate (DER)")
    srv.add_argument("--private-key", type=Path, default=None, help="server key (PEM)")
    srv.add_argument("--trust", type=Path, action="append", default=None, metavar="PATH",
                     help="trusted client cert or folder (repeatable)")  # fmt: skip
    srv.add_argument("--allow-insecure", action="store_true", help="also offer security None")
    srv.add_argument("--user", action="append", default=[], metavar="NAME:PASSWORD_ENV",
                     help="a user, password in $PASSWORD_ENV (repeatable)")  # fmt: skip
    srv.add_argument("--no-anonymous", action="store_true", help="refuse anonymous sessions")
    out = parser.add_argument_group("output")
    out.add_argument("--write-map", type=Path, default=None, metavar="TOML",
                     help="write a gateway map of these blocks")  # fmt: skip
    out.add_argument("--map-base", type=Path, default=None, metavar="TOML",
                     help="sections merged over the written map, key by key (server url "
                     "and certificates, [bus], [tuner]: deploy/opcua/site-base.toml)")  # fmt: skip
    out.add_argument("--log-dir", type=Path, default=None, help="write DIR/<loop id>.csv")
    out.add_argument("--wait-for-gateway", action="store_true",
                     help="start the clock once a client monitors every PV")  # fmt: skip
    out.add_argument("--progress", type=float, default=600.0, help="status every N simulated s")


def build_loops(args: argparse.Namespace) -> list[SimulatedLoop]:
    from plant_sim import config
    from plant_sim.process import simulation

    return config.build_loops(tuple(loop_specs(args)), simulation(args), {})


def loop_specs(args: argparse.Namespace) -> list:
    """The loops of the command line (``LoopSpec`` s), or one tank, ``tank1``."""
    from plant_sim.config import DEFAULT_LOOPS, LoopSpec

    specs = list(args.loops or [])
    rng = np.random.default_rng(args.seed)
    for k in range(args.many_foptd):
        K, tau = rng.uniform(0.5, 2.0), rng.uniform(3.0, 12.0)
        theta = rng.uniform(0.1, 0.5) * tau
        specs.append(LoopSpec.parse("foptd", f"F{k:04d}:K={K:.3f},tau={tau:.2f},theta={theta:.2f}"))
    specs = specs or list(DEFAULT_LOOPS)
    ids = [s.loop_id for s in specs]
    if len(set(ids)) != len(ids):
        raise SystemExit(f"pitune plant opcua: duplicate loop ids in {ids}")
    return specs


def security_from_args(args: argparse.Namespace) -> DcsSecurity:
    import os

    users = {}
    for item in args.user:
        name, _, env = item.partition(":")
        if not env or env not in os.environ:
            raise SystemExit(f"pitune plant opcua: --user {item}: set ${env or 'NAME'}")
        users[name] = os.environ[env]
    if args.certificate is None and not args.allow_insecure:
        raise SystemExit(
            "pitune plant opcua: give --certificate/--private-key, or --allow-insecure"
        )
    return DcsSecurity(
        certificate=args.certificate,
        private_key=args.private_key,
        trusted=args.trust,
        allow_insecure=args.allow_insecure,
        users=users or None,
        allow_anonymous=not args.no_anonymous,
    )


async def serve(args: argparse.Namespace, stop: asyncio.Event) -> int:
    loops = build_loops(args)
    dcs = SimulatedDcs(loops, port=args.port, host=args.host, security=security_from_args(args))
    async with dcs:
        if args.write_map:
            import tomli_w

            specs = {s.loop_id: s for s in loop_specs(args)}
            reg = {
                i: {
                    "scaling": s.hint().model_dump(exclude_none=True),
                    "sample_period_s": args.scan,
                    **({"extra": {"action": s.action}} if s.action != "reverse" else {}),
                }
                for i, s in specs.items()
            }
            wall_ms = args.scan * 1000.0 / args.speed if args.speed > 0 else args.scan * 1000.0
            # the monitored items' queues hold 10 s of plant time: no sample lost while
            # the gateway is slow to publish (a fast simulation scans every few ms)
            queue = max(10, min(10_000, round(10_000.0 / wall_ms)))
            defaults = {"sampling_interval_ms": wall_ms, "queue_size": queue}
            site = dcs.site_map(registration=reg, loop_defaults=defaults)
            if args.certificate is None:
                site["server"].update(security="None", allow_insecure=True)
            if args.map_base is not None:
                site = merge_map(site, args.map_base)
            args.write_map.parent.mkdir(parents=True, exist_ok=True)
            args.write_map.write_text(tomli_w.dumps(site))
        print(f"dcs: {len(loops)} PID blocks on {dcs.url} (ns={dcs.ns}), scan {args.scan:g} s, "
              f"speed {args.speed:g}x", flush=True)  # fmt: skip
        with contextlib.ExitStack() as stack:
            writers = {}
            if args.log_dir:
                for loop in loops:
                    w = TrajectoryWriter(args.log_dir / f"{loop.loop_id}.csv")
                    stack.callback(w.close)
                    writers[loop.loop_id] = w
            if args.wait_for_gateway:
                await dcs.wait_for_client(stop)
                print("dcs: the gateway monitors every block: plant clock started", flush=True)
            scans, late = await pace(dcs, args, stop, writers)
            if not stop.is_set():  # --duration reached: let the last scan's publish go out
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), 1.0)
    print(f"dcs stopped after {scans} scans (worst scan started {late:.3f} s late)",
          flush=True)  # fmt: skip
    return 0


def merge_map(site: dict, base: Path) -> dict:
    """``site`` with the tables of the TOML file ``base`` merged over it, key by key (a
    table absent from ``site`` is added); SystemExit if the file is not TOML."""
    import tomllib

    try:
        extra = tomllib.loads(base.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise SystemExit(f"pitune plant opcua: --map-base {base}: {exc}") from None
    merged = dict(site)
    for key, value in extra.items():
        old = merged.get(key)
        both = isinstance(old, dict) and isinstance(value, dict)
        merged[key] = {**old, **value} if both else value
    return merged


async def pace(dcs: SimulatedDcs, args, stop: asyncio.Event, writers: dict) -> tuple[int, float]:
    """Scan at ``speed`` times real time until ``--duration`` or ``stop``; the number of
    scans and how far behind schedule the latest one started (s)."""
    last = round(args.duration / args.scan) if args.duration is not None else None
    every = round(args.progress / args.scan) if args.progress > 0 else 0
    start = time.monotonic()
    k = 0
    late = 0.0
    while not stop.is_set() and (last is None or k < last):
        if args.speed > 0:
            delay = start + k * args.scan / args.speed - time.monotonic()
            late = max(late, -delay)
            if delay > 0:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), delay)
                if stop.is_set():
                    break
        else:
            await asyncio.sleep(0)
        scans = await dcs.scan()
        for scan, loop in zip(scans, dcs.loops, strict=True):
            if loop.loop_id in writers:
                writers[loop.loop_id].write(scan)
        if every and k % every == 0 and scans:
            s = scans[0]
            print(f"t={s.t:9.0f}s {dcs.loops[0].loop_id}: sp={s.sp:.4g} pv={s.pv:.4g} "
                  f"op={s.op:.4g} kp={s.kp:.4g} ki={s.ki:.4g}", flush=True)  # fmt: skip
        k += 1
    return k, late


def run(args: argparse.Namespace) -> int:
    import faulthandler

    faulthandler.register(signal.SIGUSR1)  # kill -USR1 <pid>: every thread's stack on stderr
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(message)s")

    async def main() -> int:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        return await serve(args, stop)

    return asyncio.run(main())
