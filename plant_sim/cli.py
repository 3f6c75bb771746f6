"""``pitune plant``: the sub-commands of :mod:`plant_sim.process` (``run``, ``plot``) plus
``opcua``, the simulated DCS behind an OPC UA server (:mod:`plant_sim.opcua_dcs`,
:mod:`plant_sim.opcua_cli`).

Only the chosen action's module is imported when it runs (asyncua loads only for ``opcua``).
"""

from __future__ import annotations

import argparse

from plant_sim import process


def add_arguments(parser: argparse.ArgumentParser) -> None:
    process.add_arguments(parser)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    opcua = sub.add_parser(
        "opcua", help="simulated DCS: the loops as PID blocks on an OPC UA server"
    )
    from plant_sim import opcua_cli

    opcua_cli.add_arguments(opcua)


def run(args: argparse.Namespace) -> int:
    if args.plant_command == "opcua":
        from plant_sim import opcua_cli

        return opcua_cli.run(args)
    return process.run(args)
