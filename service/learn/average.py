"""Checkpoint averaging: one actor whose weights are the element-wise mean of kept actors.

Imitation training at a constant learning rate leaves consecutive actors scattered around
a region of good weights; each kept actor is one draw, good on some scores and off on
others (TRAINING.md, session 22: stage K's epoch 240 settles fast, its epoch 390 adapts
best, neither does both). The mean of actors of one run (stochastic weight averaging,
Izmailov et al., UAI 2018) lands nearer the middle of that region. It is only meaningful
for actors of one lineage (one warm start, so the same basin); averaging unrelated
networks gives garbage, which :func:`average_actors` cannot detect and the evaluation will.

The result is an ordinary agent file (:func:`service.agent.model.save_actor`): its meta is
the last input's, listed last as the lineage's latest actor (the training facts the model
card prints: the lineage's time is the latest actor's), without its validation scores,
which are not the mean's, and with ``average_of`` listing every input's path, epoch, run
wall time and validation.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from service import UsageError
from service.agent.model import Actor, load_agent, save_actor


def average_actors(paths: list[Path]) -> tuple[Actor, dict]:
    """The actor with the mean weights of the agent files at ``paths`` and its meta.

    The last input gives the meta, so list the lineage's latest actor last (a run's
    ``wall_s`` counts from that run's start, so the files cannot tell). Raises UsageError
    for fewer than two distinct files, a file that is not an agent, different
    architectures or non-finite weights; FileNotFoundError for a missing file.
    """
    paths = [Path(p) for p in paths]
    if len({p.resolve() for p in paths}) != len(paths) or len(paths) < 2:
        raise UsageError("give at least two distinct agent files to average")
    lead = load_agent(paths[0])
    # one architecture, one set of parameters (the actor derives them from its config)
    agents = [lead, *(load_agent(p, lead.cfg) for p in paths[1:])]
    states = [a.actor.state_dict() for a in agents]
    mean = {}
    for key, first in states[0].items():
        stack = torch.stack([s[key].to(torch.float64) for s in states])
        if not torch.isfinite(stack).all():
            raise UsageError(f"non-finite weights in {key}")
        mean[key] = stack.mean(0).to(first.dtype)
    actor = Actor(agents[0].cfg)
    actor.load_state_dict(mean)
    meta = dict(agents[-1].meta)
    meta.pop("validation", None)  # the latest input's scores, not the mean's
    meta["average_of"] = [
        {"path": str(p), **{k: a.meta.get(k) for k in ("source", "epoch", "wall_s", "validation")}}
        for p, a in zip(paths, agents, strict=True)
    ]
    return actor, meta


# -- command line ------------------------------------------------------------------------
def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "actors", type=Path, nargs="+", help="agent files of one lineage, the latest last"
    )
    p.add_argument(
        "--out", type=Path, required=True, help="agent file to write (required: no default)"
    )


def run(args: argparse.Namespace) -> int:
    if args.out.is_dir():
        raise UsageError(f"--out {args.out} is a folder: give the agent file to write")
    try:
        actor, meta = average_actors(args.actors)
    except FileNotFoundError as err:  # a listed input: a bad command line, not a lost file
        raise UsageError(str(err)) from None
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(args.out.name + ".tmp")
    save_actor(actor, tmp, meta)
    tmp.replace(args.out)  # never a half-written agent file at --out
    print(f"wrote {args.out}: mean of {len(args.actors)} actors")
    return 0
