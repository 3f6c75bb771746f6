"""The simulated DCS's PID block (plant_sim/opcua_block.py) refuses what a DCS refuses:
a real asyncua server, scanned by hand."""

from __future__ import annotations

import asyncio

from plant_sim.config import LoopSpec, Simulation
from plant_sim.opcua_block import MAN
from plant_sim.opcua_dcs import SimulatedDcs
from service.wire.session import free_port


def test_the_simulated_block_clamps_an_operators_out_and_refuses_a_bad_mode():
    """In MAN an OUT beyond the output limits is clamped and shown clamped, a NaN one is
    refused (the output holds); a MODE other than 1, 2, 3 is refused (written back), as a
    DCS does. Unclamped, an OUT of 150 on the 0-80 L/min pump wound the PI up for the
    return to AUTO; a MODE of 99 ran as AUTO."""

    async def main() -> None:
        loop = LoopSpec("two_tank", "tank1").build(Simulation(), seed=0, t0=0.0)
        lo, hi = loop.op_limits
        async with SimulatedDcs([loop], port=free_port()) as dcs:
            block = dcs.blocks["tank1"]
            await dcs.scan()
            await dcs.set_mode("tank1", MAN)
            await dcs.set_param("tank1", "OUT", 150.0)
            (scan,) = await dcs.scan()
            assert scan.op == hi and block._read(dcs.server, "OUT") == hi
            assert loop.pi.integral[0] <= hi  # nothing stored past the limit
            await dcs.set_param("tank1", "OUT", float("nan"))
            (scan,) = await dcs.scan()
            assert scan.op == hi
            await dcs.set_param("tank1", "OUT", lo - 5.0)
            (scan,) = await dcs.scan()
            assert scan.op == lo
            await dcs.set_mode("tank1", 99)
            (scan,) = await dcs.scan()
            assert block._read(dcs.server, "MODE") == MAN and scan.op == lo  # still manual

    asyncio.run(main())
