"""The ``pitune`` console script.

Each sub-command lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``. Only the chosen sub-command's module is imported, so
``pitune --help`` and light commands start fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "train": ("service.learn.train", "train the meta-RL agent offline (recurrent PPO)"),
    "evaluate": ("service.learn.evaluate", "reproduce the paper's experiments, write reports/"),
    "tuner": ("service.daemon.main", "run the tuner daemon (Zenoh bus + admin API)"),
    "plant": ("plant_sim.cli", "run simulated plants behind a DCS-like gateway (or OPC UA)"),
    "demo": ("service.demo", "tuner + two-tank plant end to end, write demo/"),
    "bench": ("service.bench", "load benchmark of the tuner daemon"),
    "gateway": ("service.gateways.cli", "DCS gateways: OPC UA to the pitune bus; certificates"),
}


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The full parser; only ``command``'s arguments are loaded (all when None)."""
    parser = argparse.ArgumentParser(prog="pitune", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if command in (None, name):
            importlib.import_module(module).add_arguments(p)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    chosen = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(chosen if chosen in COMMANDS else "")
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    module = importlib.import_module(COMMANDS[args.command][0])
    return int(module.run(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
