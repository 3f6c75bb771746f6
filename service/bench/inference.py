"""The batched inference step for N due loops, timed in the benchmark's own process on one
thread, for ``agent.act`` and the daemon's :class:`service.agent.fast.FastPolicy`."""

from __future__ import annotations

import time

import numpy as np
import torch

from service.agent import load_agent, untrained_agent
from service.agent.fast import FastPolicy
from service.bench.config import BenchConfig
from service.daemon.settings import UNTRAINED
from service.units import DEFAULT_FORGETTING


def inference_bench(config: BenchConfig, n: int) -> dict:
    """Time one batched step of ``n`` due loops on one torch thread (min and median)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        if config.agent_weights == UNTRAINED:
            agent = untrained_agent(0)
        else:
            agent = load_agent(config.agent_weights) if config.agent_weights else load_agent()
        rng = np.random.default_rng(1)
        obs = np.column_stack(
            [np.exp(rng.normal(0, 1, (n, 2))), rng.normal(0, 0.5, n), rng.normal(0, 2, n)]
        )
        state = rng.normal(0, 0.3, (n, agent.cfg.layers, agent.cfg.hidden)).astype(np.float32)
        gamma = np.full(n, DEFAULT_FORGETTING)
        fast = FastPolicy(
            agent, workers=config.inference_workers, precision=config.inference_precision
        )
        out = {
            "loops": n,
            "torch_threads": 1,
            "workers": config.inference_workers,
            "precision": fast.precision,
        }
        for name, fn in (
            ("agent_act", lambda: agent.act(obs, state, gamma)),
            ("fast_policy", lambda: fast.step_inplace(obs, state.copy(), gamma)),
        ):
            times = []
            for _ in range(21):  # the box is noisy: a median of many
                started = time.perf_counter()
                fn()
                times.append(time.perf_counter() - started)
            out[f"{name}_ms_min"] = 1e3 * min(times)
            out[f"{name}_ms_median"] = 1e3 * float(np.median(times))
        return out
    finally:
        torch.set_num_threads(threads)
