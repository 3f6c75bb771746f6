"""pitune: online PI tuning with a meta-reinforcement-learning agent.

A tuner daemon steps the trained agent for each registered PI loop and publishes new
gains over Eclipse Zenoh to the plant's DCS gateway; the other commands train and
evaluate the agent, simulate plants and gateways, and demonstrate and benchmark it.
Run ``pitune COMMAND --help`` for a command's options, each with its default.

Each sub-command lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``. Only the chosen sub-command's module is imported, so
``pitune --help`` and light commands start fast.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import importlib
import inspect
import re
import sqlite3
import sys
import textwrap

from service import UsageError, __version__

COMMANDS: dict[str, tuple[str, str]] = {
    "train": ("service.learn.train", "train the meta-RL agent offline (recurrent PPO)"),
    "evaluate": ("service.learn.evaluate", "reproduce the paper's experiments, write a report"),
    "average": ("service.learn.average", "average the weights of kept actors of one lineage"),
    "verify-eval": (
        "service.learn.verification",
        "measure verify-or-rollback on simulated loops (false-rollback rate)",
    ),
    "tuner": ("service.daemon.main", "run the tuner daemon (Zenoh bus + admin API)"),
    "plant": ("plant_sim.cli", "run simulated plants behind a DCS-like gateway (or OPC UA)"),
    "demo": ("service.demo", "tuner + two-tank plant end to end, write demo/"),
    "bench": ("service.bench", "load benchmark of the tuner daemon"),
    "gateway": ("service.gateways.cli", "DCS gateways: OPC UA to the pitune bus; certificates"),
    "store": ("service.daemon.export", "the tuner's store: export the audit history (JSON lines)"),
}
EPILOG = """\
Quick start: `pitune demo` runs a tuner and a simulated two-tank plant for an hour of
plant time; `pitune tuner` runs the daemon (docs/tuner.md), `pitune plant run` a
simulated plant behind a gateway. Exit status 0 on success, 2 for a bad command line
(or a value a command refuses), 1 for a file that is missing or unreadable;
`pitune tuner --help` lists the daemon's other exit statuses."""


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults shown for every option (unless its help already states one), and
    descriptions and epilogs printed as written."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if "default" in text.lower() or re.search(r"\(\s*[-+]?[\d.]+(e[-+]?\d+)?\s*\)\s*$", text):
            return text  # states its default already, e.g. "(60)"
        return super()._get_help_string(action)


def attribute_docs(cls: type) -> dict[str, str]:
    """The docstrings written under a dataclass's fields (``x: int = 1`` then a string)."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError, SyntaxError):
        return {}
    docs: dict[str, str] = {}
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    for field, doc in zip(body, body[1:], strict=False):
        if (
            isinstance(field, ast.AnnAssign)
            and isinstance(field.target, ast.Name)
            and isinstance(doc, ast.Expr)
            and isinstance(doc.value, ast.Constant)
            and isinstance(doc.value.value, str)
        ):
            docs[field.target.id] = " ".join(doc.value.value.split())
    return docs


def module_field_docs(module: object) -> dict[str, str]:
    """Field docs of every dataclass a command's module defines or imports (its config)."""
    docs: dict[str, str] = {}
    for value in vars(module).values():
        if isinstance(value, type) and dataclasses.is_dataclass(value):
            for name, doc in attribute_docs(value).items():
                docs.setdefault(name, doc)
    return docs


def _subparsers(parser: argparse.ArgumentParser) -> list[argparse._SubParsersAction]:
    return [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]


def polish(parser: argparse.ArgumentParser, docs: dict[str, str]) -> None:
    """This parser and its sub-parsers: the help formatter, a description for each
    sub-command (its one-line help), a help text for each option (the config field's
    doc, or its name) so that its default is shown."""
    parser.formatter_class = HelpFormatter
    for action in parser._actions:
        if action.help is None and action.option_strings:
            action.help = docs.get(action.dest) or action.dest.replace("_", " ")
    for sub in _subparsers(parser):
        helps = {choice.dest: choice.help for choice in sub._choices_actions}
        for name, child in sub.choices.items():
            if child.description is None:
                child.description = helps.get(name)
            polish(child, docs)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The full parser; only ``command``'s arguments are loaded (all when None)."""
    description = __doc__.split("\n\nEach sub-command")[0]
    parser = argparse.ArgumentParser(
        prog="pitune", description=description, epilog=EPILOG, formatter_class=HelpFormatter
    )
    parser.add_argument("--version", action="version", version=f"pitune {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if command in (None, name):
            module = importlib.import_module(module_name)
            module.add_arguments(p)
            polish(p, module_field_docs(module))
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
    try:
        return int(module.run(args) or 0)
    except Exception as exc:
        status = _users_mistake(exc)
        if status is None:
            raise
        print(f"pitune {args.command}: {exc}", file=sys.stderr)
        return status


def _users_mistake(exc: Exception) -> int | None:
    """The exit status of a user's mistake, None for a defect (which keeps its
    traceback); the user gets one line. 2 for input the command refuses (a
    :class:`~service.UsageError`: a flag's value, a file that is not what the flag takes),
    as argparse exits for a bad command line; 1 for a file or database the command was
    pointed at that is not there (or is where a folder should be), not readable or not what
    it should be."""
    if isinstance(exc, UsageError):
        return 2
    mistakes = (FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError,
                PermissionError, sqlite3.DatabaseError)  # fmt: skip
    if isinstance(exc, mistakes):
        return 1
    kind = type(exc)  # psycopg's connection errors, without importing psycopg here
    if kind.__module__.startswith("psycopg") and kind.__name__ == "OperationalError":
        return 1
    return None


if __name__ == "__main__":
    sys.exit(main())
