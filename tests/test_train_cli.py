"""`pitune train` as a command: checked flags and agent files, a stop by Ctrl-C or SIGTERM,
resuming, the export and the agent files' facts (tiny configs: seconds)."""

import csv
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from service.agent import load_agent, save_actor
from service.agent.model import Actor, AgentConfig
from service.cli import build_parser, main
from service.learn import train
from service.learn.train import Trainer
from service.learn.train_config import TrainConfig

ROOT = Path(__file__).resolve().parents[1]
TINY = dict(
    bc_epochs=2, value_warmup=1, epochs=2, episodes=12, horizon=6, bc_horizon=6, bc_updates=2,
    bc_minibatch=5, pi_iters=3, v_iters=3, eval_every=2, eval_plants=4, eval_steps=20,
)  # fmt: skip
TINY_ARGV = [f"--{k.replace('_', '-')}={v}" for k, v in TINY.items()]


def _rows(out: Path) -> list[dict]:
    return list(csv.DictReader((out / "metrics.csv").open()))


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    return err


@pytest.mark.parametrize("flag", ["--val-robust", "--excitation-gate", "--keep-validated"])
def test_boolean_flags_take_yes_no_words_and_refuse_anything_else(flag, capsys):
    parser = build_parser("train")
    for word, value in (("true", True), ("Yes", True), ("1", True), ("no", False), ("0", False)):
        assert (
            getattr(parser.parse_args(["train", flag, word]), flag[2:].replace("-", "_")) is value
        )
    with pytest.raises(SystemExit) as info:  # was False, silently
        parser.parse_args(["train", flag, "treu"])
    assert info.value.code == 2
    assert "'treu': give true/false, 1/0 or yes/no" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--core-share", "1.5"], "--core-share 1.5: must be in [0, 1]"),
        (["--noise-prob", "2"], "--noise-prob 2.0: must be in [0, 1]"),
        (["--forgetting", "1.5"], "--forgetting 1.5: must be in (0, 1]"),
        (["--bc-epochs", "-3"], "--bc-epochs -3: must be at least 0"),
        (["--checkpoint-minutes", "-1"], "--checkpoint-minutes -1.0: must be at least 0"),
        (["--eval-every", "0"], "--eval-every 0: must be at least 1"),
        (["--bc-minibatch", "0"], "--bc-minibatch 0: must be at least 1"),
        (["--episodes", "0"], "--episodes 0: must be at least 1"),
        (["--threads", "0"], "--threads 0: must be at least 1"),
        (["--bc-lr", "nan"], "--bc-lr nan: must be > 0"),
        (["--sp-jitter", "-1"], "--sp-jitter -1.0: must be at least 0"),
        (["--sp-jitter", "0.9"], "--sp-jitter 0.9: setpoint periods must be longer than one"),
        (["--excitation-gate", "true", "--epochs", "5"], "imitation warm start: --epochs 0"),
        (["--max-minutes", "0"], "--max-minutes 0.0: must be > 0"),
        (["--resume", "--init-from", "x.pt"], "--init-from starts a new run: not with --resume"),
        (["--resume"], "holds no run to resume (no checkpoint.pt)"),
    ],
)
def test_bad_values_are_one_line_exit_2_and_create_nothing(tmp_path, capsys, argv, says):
    out = tmp_path / "run"
    assert main(["train", "--out", str(out), *TINY_ARGV, *argv]) == 2
    assert says in _one_line(capsys)
    assert not out.exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="this box has a CUDA device")
def test_a_device_torch_cannot_use_is_one_line(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", "--out", str(out), "--device", "cuda", *TINY_ARGV]) == 2
    assert "--device cuda: " in _one_line(capsys) and not out.exists()


def test_bad_agent_files_are_refused_before_anything_is_written(tmp_path, capsys):
    """--init-from: a file of another architecture, a text file, a training checkpoint;
    evaluate --weights: the latter two (tracebacks before: size mismatch, UnpicklingError
    advising weights_only=False, TypeError; the run's folder was made first)."""
    wide = tmp_path / "h64.pt"
    save_actor(Actor(AgentConfig(hidden=64)), wide, {"source": "h64"})
    text = tmp_path / "notes.pt"
    text.write_text("not an agent\n")
    run = tmp_path / "done"
    Trainer(TrainConfig(**TINY), run).run(max_epochs=1)
    capsys.readouterr()  # its progress bar
    for path, says in (
        (wide, f"{wide}: architecture hidden 64 differs from hidden 100"),
        (text, f"{text} is not an agent file (UnpicklingError)"),
        (run / "checkpoint.pt", "is a training checkpoint, not an agent file"),
    ):
        out = tmp_path / "run"
        assert main(["train", "--out", str(out), "--init-from", str(path), *TINY_ARGV]) == 2
        assert says in _one_line(capsys) and not out.exists()
        if path != wide:  # evaluate takes any architecture
            assert main(["evaluate", "--weights", str(path), "--out", str(out)]) == 2
            assert says in _one_line(capsys) and not out.exists()
        with pytest.raises(ValueError, match="not an agent file|differs from"):
            load_agent(path, AgentConfig())


def test_a_resumed_run_refuses_config_flags_that_differ_from_its_own(tmp_path, capsys):
    out = tmp_path / "run"
    Trainer(TrainConfig(**TINY), out).run(max_epochs=1)
    before = (out / "checkpoint.pt").read_bytes()
    capsys.readouterr()  # its progress bar
    assert main(["train", "--out", str(out), "--resume", "--seed", "9"]) == 2
    assert f"--seed 9: the run in {out} has 1" in _one_line(capsys)
    assert main(["train", "--out", str(out), "--resume", "--val-adapt", "yes"]) == 2
    assert "--val-adapt True: the run in" in _one_line(capsys)
    assert (out / "checkpoint.pt").read_bytes() == before and len(_rows(out)) == 1
    # the run's own values (and options that are not its config) are fine
    assert main(["train", "--out", str(out), "--resume", "--seed", "1", "--max-minutes", "5"]) == 0
    assert [int(r["epoch"]) for r in _rows(out)] == [1, 2, 3, 4, 5]


def test_ctrl_c_checkpoints_the_last_whole_epoch_and_the_run_resumes_exactly(
    tmp_path, capsys, monkeypatch
):
    """Ctrl-C inside epoch 3 (after its rollout and updates): the checkpoint is the state
    after epoch 2 (before: the one of minutes earlier, those epochs lost), exit 130 with
    how to resume; the resumed run ends where an unstopped one does, each epoch logged
    once."""
    straight = Trainer(TrainConfig(**TINY), tmp_path / "a")
    straight.run()
    out = tmp_path / "b"
    real = Trainer.ppo_epoch

    def stopped(self, train_policy):
        real(self, train_policy)  # the epoch's work done, the weights moved
        raise KeyboardInterrupt

    monkeypatch.setattr(Trainer, "ppo_epoch", stopped)
    argv = ["train", "--out", str(out), *TINY_ARGV, "--checkpoint-minutes", "100"]
    assert main(argv) == 130
    err = capsys.readouterr().err  # the progress bar, then one line
    assert "Traceback" not in err and err.strip().splitlines()[-1] == (
        f"interrupted: checkpointed at epoch 2; continue with pitune train --out {out} --resume"
    )
    assert torch.load(out / "checkpoint.pt", weights_only=True)["epoch"] == 2
    assert len(_rows(out)) == 2
    monkeypatch.setattr(Trainer, "ppo_epoch", real)
    assert main(["train", "--out", str(out), "--resume"]) == 0
    resumed = Trainer.resume(out)
    for p, q in zip(straight.actor.parameters(), resumed.actor.parameters(), strict=True):
        torch.testing.assert_close(p, q, rtol=0, atol=0)
    assert [int(r["epoch"]) for r in _rows(out)] == [1, 2, 3, 4, 5]


def test_sigterm_stops_a_real_run_checkpointed_with_status_130(tmp_path):
    out = tmp_path / "run"
    argv = [sys.executable, "-m", "service.cli", "train", "--out", str(out), "--bc-epochs", "500",
            "--epochs", "0", "--value-warmup", "0", "--episodes", "8", "--bc-horizon", "4",
            "--eval-every", "1000", "--checkpoint-minutes", "100"]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        # the log's rows (the state's copy may lag them by an epoch: 4 rows, a copy of 3)
        while not ((out / "metrics.csv").exists() and len(_rows(out)) >= 4):
            with pytest.raises(subprocess.TimeoutExpired):  # returns at once if it ended
                proc.wait(timeout=0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 130, err.decode()
    assert err.decode().strip().splitlines()[-1].startswith("interrupted: checkpointed at epoch")
    epoch = torch.load(out / "checkpoint.pt", weights_only=True)["epoch"]
    # the signal may come between an epoch's log row and the copy of its state (CI): the
    # checkpoint is the last whole epoch's, and the resume cuts the log back to it
    logged = [int(r["epoch"]) for r in _rows(out)]
    assert epoch >= 3 and logged[:epoch] == list(range(1, epoch + 1)) and len(logged) <= epoch + 1
    Trainer.resume(out)
    assert [int(r["epoch"]) for r in _rows(out)] == list(range(1, epoch + 1))


def test_resume_cuts_the_log_back_to_the_checkpoint(tmp_path):
    """A run killed between checkpoints (kill -9, power) logged epochs its checkpoint
    does not hold: the resumed run drops those rows and logs the epochs once (they were
    appended again before)."""
    straight = Trainer(TrainConfig(**TINY), tmp_path / "a")
    straight.run()
    out = tmp_path / "b"
    Trainer(TrainConfig(**TINY), out).run(max_epochs=2)
    shutil.copy(out / "checkpoint.pt", tmp_path / "at2.pt")
    Trainer.resume(out).run(max_epochs=2)
    with (out / "metrics.csv").open("a") as fh:
        fh.write("5,ppo,0.")  # a row cut by the kill
    shutil.copy(tmp_path / "at2.pt", out / "checkpoint.pt")
    resumed = Trainer.resume(out)
    assert [int(r["epoch"]) for r in _rows(out)] == [1, 2]
    assert resumed.run()
    assert [int(r["epoch"]) for r in _rows(out)] == [1, 2, 3, 4, 5]
    assert [r["mean_cost"] for r in _rows(out)] == [r["mean_cost"] for r in _rows(tmp_path / "a")]


def test_export_works_when_no_validation_scored_finite(tmp_path, monkeypatch):
    """Every validation inf (a loop unstable each time): best.pt is the first validated
    actor, so --export has a file to copy (before: No such file ... best.pt, exit 1)."""
    real = train.validate
    monkeypatch.setattr(train, "validate", lambda *a: real(*a) | {"val_score": float("inf")})
    out, export = tmp_path / "run", tmp_path / "agent.pt"
    assert main(["train", "--out", str(out), *TINY_ARGV, "--export", str(export)]) == 0
    assert export.read_bytes() == (out / "best.pt").read_bytes()
    assert load_agent(export).meta["epoch"] == 2  # the first validation's


def test_agent_files_carry_the_logs_wall_time_of_their_epoch(tmp_path):
    """meta wall_s left out the epoch it was saved at (N 65: meta 355.0, log 364.6)."""
    out = tmp_path / "run"
    Trainer(TrainConfig(**TINY, keep_validated=True), out).run()
    rows = {int(r["epoch"]): float(r["wall_s"]) for r in _rows(out)}
    for epoch in (2, 4, 5):
        meta = load_agent(out / f"val_{epoch:04d}.pt").meta
        assert meta["epoch"] == epoch and meta["wall_s"] == rows[epoch] > rows[epoch - 1]


def test_the_training_commit_is_the_packages_checkout_not_the_current_folders(
    tmp_path, monkeypatch
):
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                          text=True).stdout.strip()  # fmt: skip
    if not head:
        pytest.skip("the tests run from a copy, not a git checkout")
    other = tmp_path / "other"
    other.mkdir()
    subprocess.run(["git", "init", "-q", str(other)], check=True)
    subprocess.run(["git", "-C", str(other), "-c", "user.name=x", "-c", "user.email=x@x",
                    "commit", "-q", "--allow-empty", "-m", "x"], check=True)  # fmt: skip
    for folder in (tmp_path, other):  # no repository; another repository
        monkeypatch.chdir(folder)
        assert train._git_commit() == head
    monkeypatch.setenv("PATH", str(tmp_path))  # no git at all
    assert train._git_commit() == "unknown"
    assert Trainer(TrainConfig(**TINY), tmp_path / "run").card_meta({})["commit"] == "unknown"
