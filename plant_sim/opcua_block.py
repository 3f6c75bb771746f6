"""A simulated loop as a DCS PID block in an OPC UA address space (``pitune plant opcua``).

The block's parameters (node ids ``ns=<idx>;s=<loop>.<PARAM>``), the way DeltaV, Experion
or PCS 7 show one:

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
written back, as a DCS does. In MAN the output holds (OUT, operator-writable) and the PI
tracks it, so the return to AUTO is bumpless; an OUT beyond the output limits is clamped
(and shown clamped), a NaN one refused (an OUT of 150 on a 0-80 valve wound the PI up for
97 s at the limit after AUTO). A MODE other than 1, 2, 3 is refused: the mode in force is
written back (it ran as AUTO while the gateway's map read it as not auto).
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from datetime import UTC, datetime

import numpy as np
from asyncua import Server, ua

from plant_sim.scenario import TANK_FLOW_MAX, Scan, SimulatedLoop
from service.gateways.opcua.forms import GainForm, ITerm, PTerm

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
        if mode not in MODES.values():  # refused, as a DCS refuses it: the mode in force
            mode = self.shown["MODE"]
            await self._write(server, "MODE", mode, ts, force=True)
        lo, hi = loop.op_limits
        if mode == MAN:  # the operator's OUT, within the output limits (NaN: refused)
            out = float(self._read(server, "OUT"))
            if math.isfinite(out):
                self.op = min(
                    max(out, -math.inf if lo is None else lo), math.inf if hi is None else hi
                )
            scan = held_scan(loop, self.op)
        else:
            scan = loop.scan()
            self.op = scan.op
        self.shown["MODE"] = mode
        in_force = self.form.from_parallel(scan.kp, scan.ki)
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
    pv_true, pv = loop.read()
    loop.pi.initialise(np.array([op]), np.array([loop.error(sp, pv)]))
    target = float(loop.target.output()[0])
    kp, ki = loop.gains
    loop._advance(op, loop.load.at(elapsed))
    loop.target.step(np.array([sp]))
    loop.scans += 1
    return Scan(t=loop.t0 + elapsed, sp=sp, pv=pv, pv_true=pv_true, target=target, op=op, kp=kp,
                ki=ki, saturated=False)  # fmt: skip
