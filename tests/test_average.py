"""`pitune average`: the element-wise mean of kept actors, checked inputs, the model card."""

import json
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest
import torch

from service.agent import load_agent, save_actor, untrained_agent
from service.agent.model import Actor
from service.cli import main
from service.learn.report import write_model_card
from service.learn.train_config import TrainConfig


def _kept(tmp_path, name, seed, wall_s, epoch):
    agent = untrained_agent(seed)
    meta = {"source": "runs/x", "epoch": epoch, "wall_s": wall_s, "validation": {"val_score": 1.0}}
    save_actor(agent.actor, tmp_path / name, meta)
    return tmp_path / name


def test_the_mean_of_two_actors_is_their_weights_mean_and_steps_like_it(tmp_path):
    a = _kept(tmp_path, "val_0240.pt", 1, 1200.0, 240)
    b = _kept(tmp_path, "val_0390.pt", 2, 2300.0, 390)
    out = tmp_path / "avg" / "mean.pt"
    assert main(["average", str(a), str(b), "--out", str(out)]) == 0
    wa, wb, wm = (load_agent(p).actor.state_dict() for p in (a, b, out))
    for key in wm:
        torch.testing.assert_close(wm[key], (wa[key] + wb[key]) / 2, rtol=0, atol=1e-7)
    # an agent like any other: it steps loops
    mean = load_agent(out)
    obs = np.array([[0.5, 1.0, 0.3, -0.2]])
    delta, state = mean.act(obs, mean.initial_state(1))
    assert delta.shape == (1, 2) and np.isfinite(delta).all() and state.any()
    # the last (latest) input's facts (wall 2,300 s: the lineage's time), every input listed
    assert mean.meta["epoch"] == 390 and mean.meta["wall_s"] == 2300.0
    assert [x["epoch"] for x in mean.meta["average_of"]] == [240, 390]
    assert mean.meta["average_of"][0] == {
        "path": str(a), "source": "runs/x", "epoch": 240, "wall_s": 1200.0,
        "validation": {"val_score": 1.0},
    }  # fmt: skip
    assert "validation" not in mean.meta  # the inputs' scores are not the mean's


def test_the_model_card_names_the_averaged_actors(tmp_path):
    a = _kept(tmp_path, "a.pt", 1, 10.0, 10)
    b = _kept(tmp_path, "b.pt", 2, 20.0, 20)
    out = tmp_path / "mean.pt"
    assert main(["average", str(a), str(b), "--out", str(out)]) == 0
    metrics = json.loads((Path(__file__).parents[1] / "reports" / "metrics.json").read_text())
    write_model_card(tmp_path / "CARD.md", load_agent(out), metrics)
    card = (tmp_path / "CARD.md").read_text()
    assert f"`{a}` (epoch 10, 10.0 s into its run)" in card and f"`{b}` (epoch 20" in card
    assert "RL steps): none (a weight average" in card


def test_the_model_card_states_the_weights_own_distribution_and_selection(tmp_path):
    """The card said "a quarter of the episodes have drifting dynamics" and a selection
    without the robust and adaptation terms whatever the weights' config (v6: 0.7, both)."""
    metrics = json.loads((Path(__file__).parents[1] / "reports" / "metrics.json").read_text())
    cfg = asdict(TrainConfig(drift_prob=0.7, bc_horizon=100, val_robust=True, val_adapt=True))
    a = _kept(tmp_path, "a.pt", 1, 10.0, 10)
    b = _kept(tmp_path, "b.pt", 2, 20.0, 20)
    agent = load_agent(b)
    agent.meta |= {"train_config": cfg, "average_of": [{"path": str(a), "epoch": 10,
                                                        "wall_s": 10.0}]}  # fmt: skip
    write_model_card(tmp_path / "CARD.md", agent, metrics)
    card = " ".join((tmp_path / "CARD.md").read_text().split())
    assert "In the run that made these weights, 70% of the episodes have drifting" in card
    assert "warm-start episodes are 100 RL steps" in card and "quarter" not in card
    assert "minimises the worst of (worst step-test MSE / 0.003), (largest gain drift" in card
    assert "(the robustness conditions' worst and median MSE / their bars) and (the tau" in card
    assert "not one kept epoch but the element-wise mean of the kept actors" in card
    agent.meta = {"train_config": asdict(TrainConfig(sp_jitter=0.0))}  # one plain run
    write_model_card(tmp_path / "CARD.md", agent, metrics)
    card = " ".join((tmp_path / "CARD.md").read_text().split())
    assert "25% of the episodes" in card and "every 11 time units, as in the paper" in card
    assert "minimises the worse of (worst step-test MSE / 0.003) and (largest gain" in card
    assert "robustness conditions' worst" not in card and "element-wise mean of" not in card


@pytest.mark.parametrize(
    "case, says",
    [
        ("one", "at least two distinct"),
        ("same twice", "at least two distinct"),
        ("missing", "not found"),
        ("not an agent", "is not an agent file"),
        ("no actor", "is not an agent file"),
        ("other architecture", "architecture hidden 20 differs from hidden 100"),
        ("nan", "non-finite"),
        ("out is a folder", "is a folder: give the agent file"),
    ],
)
def test_bad_inputs_are_refused_and_nothing_is_written(tmp_path, capsys, case, says):
    a = _kept(tmp_path, "a.pt", 1, 10.0, 10)
    b = _kept(tmp_path, "b.pt", 2, 20.0, 20)
    if case == "one":
        args = [a]
    elif case == "same twice":
        args = [a, tmp_path / "." / "a.pt"]
    elif case == "missing":
        args = [a, tmp_path / "nope.pt"]
    elif case == "not an agent":
        (tmp_path / "notes.pt").write_text("kp = 1.2\n")
        args = [a, tmp_path / "notes.pt"]
    elif case == "no actor":
        torch.save({"weights": torch.zeros(3)}, tmp_path / "other.pt")
        args = [a, tmp_path / "other.pt"]
    elif case == "other architecture":
        small = Actor(replace(untrained_agent(3).cfg, hidden=20))
        save_actor(small, tmp_path / "small.pt")
        args = [a, tmp_path / "small.pt"]
    elif case == "out is a folder":
        args = [a, b]
    else:
        blob = torch.load(b, weights_only=True)
        blob["actor"]["head.0.bias"][0] = float("nan")
        torch.save(blob, b)
        args = [a, b]
    out = tmp_path / "mean.pt"
    if case == "out is a folder":  # written as out/ it left out.tmp behind and exited 1
        out.mkdir()
    assert main(["average", *map(str, args), "--out", f"{out}/"]) == 2
    err = capsys.readouterr().err  # one line on stderr
    assert says in err and len(err.strip().splitlines()) == 1
    assert not any(out.iterdir()) if out.is_dir() else not out.exists()
    assert not (tmp_path / "mean.pt.tmp").exists()
