"""``pitune`` console script (issue 17): a description, ``--version``, a description for
every sub-command and the default of every option in ``--help``."""

import argparse
import re
from pathlib import Path

import pytest

from service import __version__, cli
from service.daemon import main as daemon

pytestmark = pytest.mark.timeout(120)


def parsers(parser: argparse.ArgumentParser, name: str = "pitune"):
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, child in action.choices.items():
                yield from parsers(child, f"{name} {sub}")


def test_top_level_help_and_version(capsys):
    with pytest.raises(SystemExit) as done:
        cli.main(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out.strip() == f"pitune {__version__}"
    with pytest.raises(SystemExit):
        cli.main(["--help"])
    out = capsys.readouterr().out
    assert "The ``pitune`` console script" not in out
    assert "online PI tuning with a meta-reinforcement-learning agent" in out
    for name in cli.COMMANDS:
        assert re.search(rf"^\s+{name}\s+\w", out, re.M), name


def test_every_command_has_a_description_and_every_option_its_default():
    parser = cli.build_parser()
    seen = 0
    for name, p in parsers(parser):
        assert p.description, f"{name} has no description"
        text = p.format_help()
        for action in p._actions:
            if not action.option_strings or action.help == argparse.SUPPRESS:
                continue
            if isinstance(action, argparse._HelpAction | argparse._VersionAction):
                continue
            seen += 1
            flag = action.option_strings[0]
            # the option's help block, up to the next option
            block = re.search(
                rf"^ {{2}}{re.escape(flag)}\b.*?(?=^ {{2}}-|^\S|\Z)", text, re.M | re.S
            )
            assert block, f"{name} {flag} missing from --help"
            helped = " ".join(block.group(0).split())
            assert re.search(r"default|\(\s*[-+]?[\d.]+(e[-+]?\d+)?\s*\)", helped), (
                f"{name} {flag}: no default in {helped!r}"
            )
    assert seen > 100


def test_train_options_are_documented_from_the_config_dataclass():
    text = " ".join(cli.build_parser("train")._subparsers._group_actions[0]
                    .choices["train"].format_help().split())  # fmt: skip
    assert "--gae-lambda GAE_LAMBDA GAE's lambda. (default: 0.95)" in text
    assert "--bc-epochs BC_EPOCHS Imitation epochs before PPO. (default: 600)" in text


def test_tuner_help_lists_every_setting_and_the_exit_codes():
    text = cli.build_parser("tuner")._subparsers._group_actions[0].choices["tuner"].format_help()
    for variable in ("PITUNE_API_TOKEN", "PITUNE_QUEUE_SIZE", "PITUNE_STORE_FAILURE_EXIT_S",
                     "PITUNE_ZENOH_MULTICAST_SCOUTING", "PITUNE_LOG_FORMAT"):  # fmt: skip
        assert variable in text
    for code in daemon.EXIT_CODES:
        assert re.search(rf"^\s+{code}\s+\w", text, re.M), code


def test_docs_list_every_exit_status():
    text = (Path(__file__).parents[1] / "docs" / "tuner.md").read_text()
    documented = {int(code) for code in re.findall(r"^\| (\d+) \|", text, re.M)}
    assert documented == set(daemon.EXIT_CODES)
