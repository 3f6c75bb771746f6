"""Bad command-line input gets one clear line and changes nothing (issue 17)."""

import pytest

from plant_sim.config import LoopSpec
from plant_sim.trajectory import read_log
from service.cli import build_parser, main


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["demo", "--minutes", "5"], "at least 21 minutes"),
        (["demo", "--minutes", "0"], "at least 21 minutes"),
        (["demo", "--minutes", "inf"], "inf: at most 1e+06 minutes"),
        (["demo", "--minutes", "2e6"], "2e6: at most 1e+06 minutes"),
        (["demo", "--minutes", "nan"], "nan: at least 21 minutes"),
        (["demo", "--speed", "-1"], "a speed factor in (0, 10000]"),
        (["demo", "--noise", "-1"], "noise amplitude in [0, 10] cm"),
        (["plant", "run", "--speed", "-5"], "--speed: -5: must be >= 0"),
        (["plant", "run", "--duration", "0"], "--duration: 0: must be > 0"),
        (["plant", "run", "--foptd", "f1:K=2,tau=-20,theta=5"], "tau out of range"),
        (["plant", "run", "--foptd", "f1:K=2,tau=20"], "missing theta"),
        (["plant", "run", "--gain-range", "0.5"], "--gain-range: 0.5: must be > 1"),
        (["plant", "run", "--gain-range", "0"], "--gain-range: 0: must be > 1"),
        (["plant", "run", "--t0", "nan"], "--t0: nan: must be >="),
        (["demo", "--seed", "-1"], "--seed: -1: must be >= 0"),
        (["plant", "plot", "x.csv", "-o", "x.xyz"], "x.xyz: give a file ending in .eps,"),
        (["plant", "run", "--seed", "-1"], "--seed: -1: must be >= 0"),
        (["plant", "opcua", "--seed", "-1"], "--seed: -1: must be >= 0"),
        (["verify-eval", "--loops", "0"], "--loops: 0: at least 1"),
        (["gateway", "certs", "--out", "x", "--days", "0"], "at least 1 day"),
    ],
)
def test_bad_arguments_are_refused_with_a_reason(argv, says, capsys):
    with pytest.raises(SystemExit) as info:
        build_parser(argv[0]).parse_args(argv)
    assert info.value.code == 2
    assert says in capsys.readouterr().err


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("f1:K=2,tau=20,theta=-1", "theta out of range"),
        ("f1:K=nan,tau=20,theta=1", "K out of range"),
        ("f1:K=2,tau=20,theta=1,lo=3,hi=-3", "lo < hi"),
        ("f1:K=1e12,tau=20,theta=1", "less than or equal to 1000000000"),
    ],
)
def test_loop_specs_are_checked_when_parsed(text, says):
    with pytest.raises(ValueError, match=says.replace("(", r"\(")):
        LoopSpec.parse("foptd", text)
    assert LoopSpec.parse("foptd", "f1:K=2,tau=20,theta=5,lo=-3,hi=3").params["lo"] == -3.0


def test_tank_setpoints_are_checked_against_the_tanks_own_defaults():
    """A tank's setpoints default to 50 and 60 cm (not the FOPTD loops' -1 and 1): lo = 45
    alone is a valid schedule, hi = 40 alone an inverted one; and a level the full pump
    cannot hold (101 cm) is refused."""
    assert LoopSpec.parse("two_tank", "tank1:lo=45").params == {"lo": 45.0}
    for text in ("tank1:hi=40", "tank1:lo=20,hi=110", "tank1:lo=-5,hi=30"):
        with pytest.raises(ValueError, match="lo < hi|tank setpoints within"):
            LoopSpec.parse("two_tank", text)


def test_a_file_that_is_not_there_or_not_a_database_is_one_line(tmp_path, capsys):
    not_db = tmp_path / "notes.db"
    not_db.write_text("not a database")
    for argv, says in (
        (["store", "export", "--db", str(not_db)], "pitune store: file is not a database"),
        (["plant", "plot", str(tmp_path / "none.csv"), "-o", str(tmp_path / "x.png")],
         "No such file or directory"),
    ):  # fmt: skip
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert says in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_paths_for_child_processes_are_made_absolute_against_the_callers_folder(
    tmp_path, monkeypatch
):
    """The demo's and the bench's tuner runs in the checkout: a relative path must name
    the file in the folder the command was run from (tests/test_demo_cli.py runs one)."""
    monkeypatch.chdir(tmp_path)
    bench = build_parser("bench").parse_args(["bench", "--agent-weights", "v3.pt"])
    assert bench.agent_weights == str(tmp_path / "v3.pt")
    argv = ["demo", "--agent-weights", "untrained", "--workdir", "wd"]
    demo = build_parser("demo").parse_args(argv)
    assert (demo.agent_weights, demo.workdir) == ("untrained", tmp_path / "wd")


def test_a_file_that_is_not_a_trajectory_log_is_one_line(tmp_path, capsys):
    empty, other = tmp_path / "empty.csv", tmp_path / "notes.csv"
    empty.write_text("")
    other.write_text("hello,world\n")
    numbers = tmp_path / "bad.csv"
    numbers.write_text("t,sp,pv,pv_true,target,kp,ki,op\n0,1,2,2,3,4,5,x\n")
    for log, says in ((empty, "empty, not a trajectory log"), (other, "header ['hello'"),
                      (numbers, "not a trajectory log: could not convert")):  # fmt: skip
        assert main(["plant", "plot", str(log), "-o", str(tmp_path / "x.png")]) == 1
        err = capsys.readouterr().err
        assert err.startswith(f"pitune plant plot: {log}: ") and says in err, err
        assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.png").exists()


def test_a_log_from_before_pv_true_still_reads_its_measured_pv_as_the_true_one(tmp_path):
    """Logs written before session 41 have no ``pv_true`` column: read, not refused, with
    the measured PV in its place (their MSE included the noise then too)."""
    old = tmp_path / "old.csv"
    old.write_text("t,sp,pv,target,kp,ki,op\n0,1,2,3,4,5,6\n1,1,2.5,3,4,5,6\n")
    log = read_log(old)
    assert log.pv.tolist() == log.pv_true.tolist() == [2.0, 2.5]
    assert (log.target.tolist(), log.op.tolist()) == ([3.0, 3.0], [6.0, 6.0])
