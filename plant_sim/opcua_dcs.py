"""``pitune plant opcua``: a simulated DCS that exposes its PID blocks over OPC UA.

The project's simulated loops (:mod:`plant_sim.scenario`: the two-tank level loop and
FOPTD loops) run behind an asyncua server, each as a PID block in a DCS-like form, the
way DeltaV, Experion or PCS 7 show one (node ids ``ns=<idx>;s=<loop>.<PARAM>``):

======== ======= =========================================================================
param    type    meaning
======== ======= =========================================================================
SP       Double  setpoint, PV units (the schedule of the simulated loop)
PV       Double  measurement; written last in each scan, with the scan's source timestamp
OUT      Double  controller output; an operator may write it in MAN
MODE     Int32   1 MAN, 2 AUTO, 3 CAS (:data:`MODES`); operators write it
GAIN     Double  controller gain, dimensionless (%/% of the PV and OUT spans)
RESET    Double  integral time, minutes per repeat (ideal form)
TUNE_EN  Boolean the block accepts tuning from pitune (operators set it)
OUT_HI_ACT, OUT_LO_ACT  Boolean  the output is at its high / low limit
OUT_HI_LIM, OUT_LO_LIM  Double   output limits (read only)
======== ======= =========================================================================

A GAIN or RESET written by a client takes effect at the next scan, bumplessly; a value
outside the block's range (the loop's gain range) is clamped and the clamped value
written back, as a DCS does. :meth:`SimulatedDcs.lock_gains` makes GAIN and RESET read
only (a DCS that refuses the write). In MAN the output holds (OUT, operator-writable) and
the PI tracks it, so the return to AUTO is bumpless.

Time: source timestamps are the plant clock, ``epoch + t``: at ``--speed 1`` that is
wall-clock time; faster simulations stamp their values with simulated time, which the
gateway passes through as the samples' ``t``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import math
import signal
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from asyncua import Server, ua
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions

from plant_sim.scenario import TANK_FLOW_MAX, Scan, SimulatedLoop
from plant_sim.trajectory import TrajectoryWriter
from service.gateways.opcua.forms import GainForm, ITerm, PTerm

log = logging.getLogger("pitune.dcs_sim")
NAMESPACE = "urn:pitune:dcs-sim"
SERVER_URI = "urn:pitune:dcs-sim:server"
MAN, AUTO, CAS = 1, 2, 3
MODES = {"MAN": MAN, "AUTO": AUTO, "CAS": CAS}
AUTO_VALUES = [AUTO, CAS]
TANK_PV_SPAN = 120.0
"""The tank's level transmitter range, cm (0-120)."""


@dataclass(frozen=True)
class BlockScale:
    """The PV and OUT spans of a block: GAIN is shown in %/% of them."""

    pv_span: float
    op_span: float

    @property
    def form(self) -> GainForm:
        return GainForm(p=PTerm.gain, i=ITerm.reset_min, pv_span=self.pv_span, op_span=self.op_span)


def block_scale(loop: SimulatedLoop) -> BlockScale:
    if loop.kind == "two_tank":
        return BlockScale(TANK_PV_SPAN, TANK_FLOW_MAX)
    lo, hi = loop.settings.sp_low, loop.settings.sp_high
    return BlockScale(max(4.0 * (hi - lo), 1e-6), 100.0)


class UserManager:
    """Users with passwords (role User), and anonymous sessions if allowed."""

    def __init__(self, users: dict[str, str], allow_anonymous: bool) -> None:
        self.users = users
        self.allow_anonymous = allow_anonymous

    def get_user(self, iserver, username=None, password=None, certificate=None):
        if username is None:
            return User(role=UserRole.User, name="anonymous") if self.allow_anonymous else None
        if self.users.get(username) == password:
            return User(role=UserRole.User, name=username)
        return None


class PidBlock:
    """One loop as a DCS PID block in the address space."""

    PARAMS = ("SP", "PV", "OUT", "MODE", "GAIN", "RESET", "TUNE_EN", "OUT_HI_ACT", "OUT_LO_ACT",
              "OUT_HI_LIM", "OUT_LO_LIM")  # fmt: skip

    def __init__(self, loop: SimulatedLoop, ns: int) -> None:
        self.loop = loop
        self.ns = ns
        self.form = block_scale(loop).form
        self.ids = {p: ua.NodeId(f"{loop.loop_id}.{p}", ns) for p in self.PARAMS}
        self.shown: dict[str, object] = {}
        self.op = 0.0
        self.writes_seen = 0

    def node(self, param: str) -> str:
        """The node id string of a parameter, as a map file names it."""
        return f"ns={self.ns};s={self.loop.loop_id}.{param}"

    async def create(self, server: Server, folder, epoch: float) -> None:
        """The block's nodes, with the values of the loop's last scan (a DCS restarted
        mid-run shows where the plant is), stamped with that scan's time."""
        loop = self.loop
        obj = await folder.add_object(ua.NodeId(loop.loop_id, self.ns), loop.loop_id)
        p, i = self.form.from_parallel(*loop.gains)
        lo, hi = loop.op_limits
        self.op = float(loop.pi.output()[0])
        last = (loop.scans - 1) * loop.dt
        ts = datetime.fromtimestamp(epoch + loop.t0 + last, UTC)
        initial = {
            "SP": (loop.sp.at(max(last, 0.0)), ua.VariantType.Double, False),
            "PV": (loop._measure(), ua.VariantType.Double, False),
            "OUT": (self.op, ua.VariantType.Double, True),
            "MODE": (AUTO, ua.VariantType.Int32, True),
            "GAIN": (p, ua.VariantType.Double, True),
            "RESET": (i, ua.VariantType.Double, True),
            "TUNE_EN": (True, ua.VariantType.Boolean, True),
            "OUT_HI_ACT": (False, ua.VariantType.Boolean, False),
            "OUT_LO_ACT": (False, ua.VariantType.Boolean, False),
            "OUT_HI_LIM": (math.inf if hi is None else hi, ua.VariantType.Double, False),
            "OUT_LO_LIM": (-math.inf if lo is None else lo, ua.VariantType.Double, False),
        }
        for param, (value, vtype, writable) in initial.items():
            var = await obj.add_variable(self.ids[param], param, ua.Variant(value, vtype))
            if writable:
                await var.set_writable()
            dv = ua.DataValue(ua.Variant(value, vtype), SourceTimestamp=ts, ServerTimestamp=ts)
            await server.write_attribute_value(self.ids[param], dv)
            self.shown[param] = value

    # -- one scan --------------------------------------------------------------------
    def _read(self, server: Server, param: str):
        aspace = server.iserver.aspace
        return aspace.read_attribute_value(self.ids[param], ua.AttributeIds.Value).Value.Value

    async def _write(self, server: Server, param: str, value, ts: datetime, force=False) -> None:
        if not force and self.shown.get(param) == value:
            return
        self.shown[param] = value
        vtype = {
            bool: ua.VariantType.Boolean,
            int: ua.VariantType.Int32,
        }.get(type(value), ua.VariantType.Double)
        dv = ua.DataValue(ua.Variant(value, vtype), SourceTimestamp=ts, ServerTimestamp=ts)
        await server.write_attribute_value(self.ids[param], dv)

    async def scan(self, server: Server, epoch: float) -> Scan:
        loop = self.loop
        ts = datetime.fromtimestamp(epoch + loop.t0 + loop.scans * loop.dt, UTC)
        # gains written by a client since the last scan: bumpless, clamped to the range
        p, i = self._read(server, "GAIN"), self._read(server, "RESET")
        if (p, i) != (self.shown["GAIN"], self.shown["RESET"]):
            self.writes_seen += 1
            with contextlib.suppress(ValueError):  # zero or negative: keep the gains in force
                loop.apply_gains(*self.form.to_parallel(p, i))
            self.shown["GAIN"], self.shown["RESET"] = p, i
        mode = self._read(server, "MODE")
        if mode == MAN:
            self.op = float(self._read(server, "OUT"))
            scan = held_scan(loop, self.op)
        else:
            scan = loop.scan()
            self.op = scan.op
        self.shown["MODE"] = mode
        in_force = self.form.from_parallel(scan.kp, scan.ki)
        lo, hi = loop.op_limits
        await self._write(server, "SP", float(scan.sp), ts)
        await self._write(server, "OUT", float(scan.op), ts, force=True)
        await self._write(server, "OUT_HI_ACT", bool(hi is not None and scan.op >= hi), ts)
        await self._write(server, "OUT_LO_ACT", bool(lo is not None and scan.op <= lo), ts)
        if not (_close(in_force[0], p) and _close(in_force[1], i)):  # clamped: show it
            await self._write(server, "GAIN", float(in_force[0]), ts, force=True)
            await self._write(server, "RESET", float(in_force[1]), ts, force=True)
        await self._write(server, "PV", float(scan.pv), ts, force=True)  # last: the trigger
        return scan


def _close(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=0.0)


def held_scan(loop: SimulatedLoop, op: float) -> Scan:
    """A scan in manual: the output holds at ``op`` and the PI tracks it (bumpless back)."""
    elapsed = loop.scans * loop.dt
    sp = loop.sp.at(elapsed)
    pv = loop._measure()
    if loop.settings.noise:
        pv += float(loop.rng.uniform(-loop.settings.noise, loop.settings.noise))
    loop.pi.initialise(np.array([op]), np.array([sp - pv]))
    target = float(loop.target.output()[0])
    kp, ki = loop.gains
    loop._advance(op, loop.load.at(elapsed))
    loop.target.step(np.array([sp]))
    loop.scans += 1
    return Scan(t=loop.t0 + elapsed, sp=sp, pv=pv, target=target, op=op, kp=kp, ki=ki,
                saturated=False)  # fmt: skip


@dataclass
class DcsSecurity:
    """How the simulated server is secured (all None/empty: security None only)."""

    certificate: Path | None = None
    private_key: Path | None = None
    trusted: list[Path] | None = None
    """Client certificates (files or folders) allowed to connect; None: any valid one."""
    allow_insecure: bool = False
    users: dict[str, str] | None = None
    allow_anonymous: bool = True


class SimulatedDcs:
    """An asyncua server around simulated loops; ``async with`` starts and stops it."""

    def __init__(
        self,
        loops: list[SimulatedLoop],
        *,
        port: int,
        host: str = "127.0.0.1",
        security: DcsSecurity | None = None,
        epoch: float | None = None,
    ) -> None:
        self.loops = loops
        self.url = f"opc.tcp://{host}:{port}/pitune/dcs"
        self.security = security or DcsSecurity(allow_insecure=True)
        self.epoch = float(math.floor(time.time()) if epoch is None else epoch)
        self.server: Server | None = None
        self.blocks: dict[str, PidBlock] = {}
        self.ns = 0

    async def start(self) -> SimulatedDcs:
        sec = self.security
        users = UserManager(sec.users or {}, sec.allow_anonymous)
        server = Server(user_manager=users)
        await server.init()
        server.set_endpoint(self.url)
        server.set_server_name("pitune simulated DCS")
        await server.set_application_uri(SERVER_URI)
        policies = []
        if sec.certificate is not None:
            await server.load_certificate(str(sec.certificate))
            await server.load_private_key(str(sec.private_key))
            policies += [
                ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
                ua.SecurityPolicyType.Basic256Sha256_Sign,
            ]
            if sec.trusted is not None:
                store = TrustStore(list(sec.trusted), [])
                await store.load()
                options = (
                    CertificateValidatorOptions.TRUSTED_VALIDATION
                    | CertificateValidatorOptions.PEER_CLIENT
                )
                server.set_certificate_validator(CertificateValidator(options, store))
        if sec.allow_insecure:
            policies.append(ua.SecurityPolicyType.NoSecurity)
        server.set_security_policy(policies)
        tokens = [ua.UserNameIdentityToken] if sec.users else []
        if sec.allow_anonymous:
            tokens.append(ua.AnonymousIdentityToken)
        server.set_identity_tokens(tokens)
        self.ns = await server.register_namespace(NAMESPACE)
        folder = await server.nodes.objects.add_folder(ua.NodeId("PID", self.ns), "PID")
        for loop in self.loops:
            block = PidBlock(loop, self.ns)
            await block.create(server, folder, self.epoch)
            self.blocks[loop.loop_id] = block
        await server.start()
        self.server = server
        return self

    async def stop(self, timeout: float = 10.0) -> None:
        """Stop the server. asyncua's stop can wait forever for a client connection it did
        not close (seen after clients reconnected): give up after ``timeout``."""
        if self.server is not None:
            server, self.server = self.server, None
            try:
                await asyncio.wait_for(server.stop(), timeout)
            except TimeoutError:
                log.warning("OPC UA server stop timed out after %g s", timeout)

    async def __aenter__(self) -> SimulatedDcs:
        return await self.start()

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    async def scan(self) -> list[Scan]:
        """One scan of every block, in order."""
        assert self.server is not None, "not started"
        scans = []
        for k, block in enumerate(self.blocks.values()):
            if k and k % 20 == 0:
                await asyncio.sleep(0)  # let the server answer its clients mid-scan
            scans.append(await block.scan(self.server, self.epoch))
        return scans

    # -- what an operator or engineer does at the console -----------------------------
    async def set_param(self, loop_id: str, param: str, value) -> None:
        block = self.blocks[loop_id]
        vtype = {bool: ua.VariantType.Boolean, int: ua.VariantType.Int32}.get(
            type(value), ua.VariantType.Double
        )
        loop = block.loop  # stamped with the time of the last scan, as the DCS would
        ts = datetime.fromtimestamp(self.epoch + loop.t0 + (loop.scans - 1) * loop.dt, UTC)
        dv = ua.DataValue(ua.Variant(value, vtype), SourceTimestamp=ts, ServerTimestamp=ts)
        await self.server.write_attribute_value(block.ids[param], dv)

    async def set_mode(self, loop_id: str, mode: int) -> None:
        await self.set_param(loop_id, "MODE", int(mode))

    async def set_tuning_enable(self, loop_id: str, enabled: bool) -> None:
        await self.set_param(loop_id, "TUNE_EN", bool(enabled))

    async def lock_gains(self, loop_id: str, locked: bool = True) -> None:
        """Make GAIN and RESET read-only to clients (writes are refused) or writable."""
        block = self.blocks[loop_id]
        for param in ("GAIN", "RESET"):
            node = self.server.get_node(block.ids[param])
            await node.set_writable(not locked)

    def monitored(self) -> set[ua.NodeId]:
        """The nodes the server's clients monitor."""
        subs = self.server.iserver.subscription_service.subscriptions.values()
        return {
            m.read_value_id.NodeId
            for s in subs
            for m in s.monitored_item_srv._monitored_items.values()
            if m.read_value_id is not None
        }

    async def wait_for_client(self, stop: asyncio.Event) -> None:
        """Until a client monitors every block's PV (or ``stop``)."""
        pvs = {b.ids["PV"] for b in self.blocks.values()}
        while not stop.is_set() and not pvs <= self.monitored():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), 0.02)

    def gains(self, loop_id: str) -> tuple[float, float]:
        """(kp, ki) in force in the simulated loop."""
        return self.blocks[loop_id].loop.gains

    def site_map(
        self,
        *,
        limits_factor: float | None = None,
        registration: dict[str, dict] | None = None,
        loop_defaults: dict | None = None,
        **server: object,
    ) -> dict:
        """A map file (as a dict, TOML-ready) for a gateway of these blocks; the hard
        limits are the blocks' present values divided and multiplied by ``limits_factor``
        (default: each loop's gain range, what the simulated block itself accepts);
        ``registration``: loop id -> its [loops.registration] table."""
        loops = []
        for block in self.blocks.values():
            p0, i0 = block.form.from_parallel(*block.loop.gains)
            r = limits_factor or block.loop.settings.gain_range
            extra = dict(loop_defaults or {})
            if registration and block.loop.loop_id in registration:
                extra["registration"] = registration[block.loop.loop_id]
            loops.append(
                {
                    **extra,
                    "id": block.loop.loop_id,
                    "sp": block.node("SP"),
                    "pv": block.node("PV"),
                    "op": block.node("OUT"),
                    "mode": block.node("MODE"),
                    "auto_values": AUTO_VALUES,
                    "p": block.node("GAIN"),
                    "i": block.node("RESET"),
                    "form": block.form.model_dump(mode="json"),
                    "tuning_enable": block.node("TUNE_EN"),
                    "at_high_limit": block.node("OUT_HI_ACT"),
                    "at_low_limit": block.node("OUT_LO_ACT"),
                    "limits": {"p": [p0 / r, p0 * r], "i": [i0 / r, i0 * r]},
                }
            )
        return {"server": {"url": self.url, **server}, "loops": loops}


# -- command line ----------------------------------------------------------------------
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
                i: {"scaling": s.hint().model_dump(exclude_none=True), "sample_period_s": args.scan}
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
