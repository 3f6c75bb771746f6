"""``pitune plant opcua``: a simulated DCS that exposes its PID blocks over OPC UA.

The project's simulated loops (:mod:`plant_sim.scenario`: the two-tank level loop and
FOPTD loops) run behind an asyncua server, each as a PID block in a DCS-like form
(:mod:`plant_sim.opcua_block`); :class:`SimulatedDcs` is the server, its security and
what an operator does at the console (mode, tuning enable, a write lock on the gains:
:meth:`SimulatedDcs.lock_gains` makes GAIN and RESET read only, a DCS that refuses the
write). The command line is :mod:`plant_sim.opcua_cli`.

Time: source timestamps are the plant clock, ``epoch + t``: at ``--speed 1`` that is
wall-clock time; faster simulations stamp their values with simulated time, which the
gateway passes through as the samples' ``t``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from asyncua import Server, ua
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions

from plant_sim.opcua_block import AUTO_VALUES, PidBlock
from plant_sim.scenario import Scan, SimulatedLoop

log = logging.getLogger("pitune.dcs_sim")
NAMESPACE = "urn:pitune:dcs-sim"
SERVER_URI = "urn:pitune:dcs-sim:server"


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
