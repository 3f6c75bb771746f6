"""The benchmark's simulated loops: N FOPTD plants under PI control, in phase groups.

The loops are split into phase groups ``--tick`` apart, so at 1 Hz and 10 ms ticks
every 10 ms one hundredth of the loops is sampled; their plant time constants are drawn
from ``--tau``, so their RL periods, and RL steps, are spread too (``--aligned``: one
group and one time constant, every loop due in the same sample). The gains the tuner
sends back are applied bumplessly between samples. Each sample's publish time is kept
(a ring of :data:`RING` per loop) to match the gains message that answers it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from plant_sim import FOPTDBatch, PIBatch
from plant_sim.tunings import simc_paper, to_parallel
from service.bench.config import GATEWAY, BenchConfig

RING = 16
"""Sent-time stamps kept per loop (samples back in time a gains message may refer to)."""


@dataclass
class Group:
    """Loops sampled at the same instants (one phase of the sample clock)."""

    offset: float
    index: np.ndarray
    """Global loop indices."""
    plant: FOPTDBatch
    pi: PIBatch
    sp_half: np.ndarray
    sp_phase: np.ndarray
    ids: list[str]
    sent: np.ndarray
    """(n, RING) monotonic publish time of sample k at column k % RING."""
    sent_k: np.ndarray
    pending: list = field(default_factory=list)


class Fleet:
    """N FOPTD plants under PI control in phase groups; gains applied bumplessly."""

    def __init__(self, config: BenchConfig) -> None:
        n, rng = config.loops, np.random.default_rng(config.seed)
        self.n, self.period = n, 1.0 / config.rate
        self.ids = [f"L{i:05d}" for i in range(n)]
        gateways = (
            [GATEWAY]
            if config.gateways == 1
            else [f"{GATEWAY}-{g}" for g in range(config.gateways)]
        )
        self.where = {}
        lo, hi = config.tau
        if config.aligned:
            tau = np.full(n, math.sqrt(lo * hi))
        else:
            tau = np.exp(rng.uniform(math.log(lo), math.log(hi), n))
        K = np.exp(rng.uniform(math.log(0.5), math.log(2.0), n))
        theta = tau * rng.uniform(0.1, 0.5, n)
        kp, ki = to_parallel(*simc_paper(K, tau, theta))
        detune = np.exp(rng.uniform(math.log(0.3), math.log(3.0), (2, n)))
        self.kp0, self.ki0 = kp * detune[0], ki * detune[1]
        hint_k = K * np.exp(rng.normal(0.0, 0.2, n))
        self.registrations = [
            {
                "id": self.ids[i],
                "kp": float(self.kp0[i]),
                "ki": float(self.ki0[i]),
                "sample_period_s": self.period,
                "scaling": None
                if config.no_hint
                else {
                    "k_hat": float(hint_k[i]),
                    "tau_hat": float(tau[i]),
                    "pv_scale": 1.0,
                },
                # every due loop is stepped, whatever its setpoint does: the worst case
                "guard": {"excitation_periods": 0.0, **(config.guard or {})},
                **({"gateway": gateways[i % len(gateways)]} if config.batched_gains else {}),
            }
            for i in range(n)
        ]
        n_groups = 1 if config.aligned else max(1, min(n, round(self.period / config.tick)))
        self.groups: list[Group] = []
        for g in range(n_groups):
            idx = np.arange(g, n, n_groups)
            plant = FOPTDBatch(K[idx], tau[idx], theta[idx], dt=self.period, noise_std=0.01,
                               seed=rng.integers(1 << 31))  # fmt: skip
            plant.reset(0.0)
            pi = PIBatch(self.kp0[idx], self.ki0[idx], dt=self.period)
            pi.initialise(0.0)
            self.groups.append(
                Group(
                    offset=g * self.period / n_groups,
                    index=idx,
                    plant=plant,
                    pi=pi,
                    sp_half=rng.uniform(20.0, 60.0, idx.size),
                    sp_phase=rng.uniform(0.0, 120.0, idx.size),
                    ids=[self.ids[i] for i in idx],
                    sent=np.full((idx.size, RING), np.nan),
                    sent_k=np.full((idx.size, RING), -1, np.int64),
                )
            )
            for j, i in enumerate(idx):
                self.where[self.ids[i]] = (g, j)

    def scan(self, g: int, k: int, t0: float) -> tuple[float, list[dict]]:
        """Sample group ``g`` at its ``k``-th instant: plant time and the samples."""
        grp = self.groups[g]
        self._apply(grp)
        t = t0 + k * self.period + grp.offset
        sp = np.where(((t + grp.sp_phase) // grp.sp_half) % 2 == 0, 1.0, -1.0)
        pv = grp.plant.measure()
        u = grp.pi.step(sp - pv)
        grp.plant.step(u)
        ids, sps, pvs = grp.ids, sp.tolist(), pv.tolist()
        kps, kis = grp.pi.kp.tolist(), grp.pi.ki.tolist()
        samples = [
            {"loop_id": ids[j], "t": t, "sp": sps[j], "pv": pvs[j], "kp": kps[j], "ki": kis[j]}
            for j in range(len(ids))
        ]
        return t, samples

    def stamp(self, g: int, k: int, wall: float) -> None:
        grp = self.groups[g]
        grp.sent[:, k % RING] = wall
        grp.sent_k[:, k % RING] = k

    def sent_time(self, loop_id: str, t: float, t0: float) -> float:
        """Monotonic publish time of the loop's sample at plant time ``t`` (NaN: unknown)."""
        g, j = self.where[loop_id]
        grp = self.groups[g]
        k = round((t - t0 - grp.offset) / self.period)
        if grp.sent_k[j, k % RING] != k:
            return math.nan
        return float(grp.sent[j, k % RING])

    def offer(self, loop_id: str, kp: float, ki: float) -> None:
        g, j = self.where[loop_id]
        self.groups[g].pending.append((j, kp, ki))

    @staticmethod
    def _apply(grp: Group) -> None:
        if not grp.pending:
            return
        j, kp, ki = (np.asarray(v) for v in zip(*grp.pending, strict=True))
        grp.pending.clear()
        pi = grp.pi
        pi.integral[j] -= (kp - pi.kp[j]) * pi.e_last[j]  # bumpless, as set_gains
        pi.kp[j], pi.ki[j] = kp, ki
