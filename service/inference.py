"""Fast batched inference of the agent's actor: :meth:`Agent.act` for the tuner's hot path.

:class:`FastPolicy` wraps an :class:`~service.agent.Agent`'s weights and computes exactly
what ``agent.act`` computes (same float32 arithmetic, equal to about 1e-6), but built for
large batches on one CPU core:

* the batch is processed in blocks of ``block`` loops whose intermediates (gates, hidden
  states, head activations) live in buffers allocated once and reused, so they stay in
  the core's L2 cache and no call allocates (fresh multi-megabyte tensors cost page
  faults and memory bandwidth, which dominated the naive call at 10,000 loops);
* each GRU layer is written out (two GEMMs into preallocated gates, in-place
  sigmoid/tanh, ``h' = n + z (h - n)``) with the r/z biases of both GEMMs folded into
  one, and the weights stored pre-transposed and contiguous;
* the state is read from and written to the caller's ``(n, layers, hidden)`` float32
  array in place (:meth:`step_inplace`), with no transposes or copies of the whole batch.

The GRU equations (PyTorch's ``nn.GRU``, gates ordered r, z, n), with the paper's
forgetting factor ``gamma`` scaling the previous hidden state of every layer::

    h = gamma h_prev
    r = sigmoid(W_ir x + b_ir + W_hr h + b_hr)
    z = sigmoid(W_iz x + b_iz + W_hz h + b_hz)
    n = tanh(W_in x + b_in + r (W_hn h + b_hn))
    h' = (1 - z) n + z h = n + z (h - n)
"""

from __future__ import annotations

import numpy as np
import torch
from torch.nn import functional as F

from service.agent import GAIN_FLOOR, MAX_LOG_STEP, Agent

LEAKY_SLOPE = 0.01
"""``nn.LeakyReLU``'s default negative slope (the actor's head uses the default)."""


class FastPolicy:
    """Numerically equal, allocation-free replacement of ``agent.act`` for numpy callers."""

    def __init__(self, agent: Agent, block: int = 512) -> None:
        self.agent = agent
        self.block = int(block)
        cfg = agent.cfg
        self.layers, self.hidden = cfg.layers, cfg.hidden
        gru, head = agent.actor.gru, agent.actor.head
        hid = cfg.hidden
        self._gru = []
        with torch.no_grad():
            for layer in range(cfg.layers):
                w_ih = getattr(gru, f"weight_ih_l{layer}").detach().float()
                w_hh = getattr(gru, f"weight_hh_l{layer}").detach().float()
                b_ih = getattr(gru, f"bias_ih_l{layer}").detach().float().clone()
                b_hh = getattr(gru, f"bias_hh_l{layer}").detach().float().clone()
                b_i = b_ih.clone()
                b_i[: 2 * hid] += b_hh[: 2 * hid]  # r and z: both biases add up
                self._gru.append(
                    (w_ih.t().contiguous(), w_hh.t().contiguous(), b_i, b_hh[2 * hid :].clone())
                )
            linears = [m for m in head if isinstance(m, torch.nn.Linear)]
            self._head = [(m.weight.detach().float().t().contiguous(), m.bias.detach().float())
                          for m in linears]  # fmt: skip
        self._allocate(self.block)

    def _allocate(self, b: int) -> None:
        hid, width = self.hidden, self._head[0][0].shape[1]
        e = torch.empty
        self._obs = e(b, 4)
        self._x = e(b, 4)
        self._gi = e(b, 3 * hid)
        self._gh = e(b, hid)
        self._h = e(b, hid)
        self._a1, self._a2 = e(b, width), e(b, self._head[1][0].shape[1])
        self._mean = e(b, 2)
        self._tmp = e(b, 2)

    @torch.inference_mode()
    def step_inplace(self, obs: np.ndarray, state: np.ndarray, forgetting) -> np.ndarray:
        """Step ``n`` loops; ``state`` ((n, layers, hidden) float32, C-contiguous) is updated.

        Returns ``delta`` (n, 2) float64, as ``agent.act`` does. ``forgetting``: scalar
        or (n,).
        """
        n = obs.shape[0]
        if obs.shape != (n, 4):
            raise ValueError(f"obs must have shape (n, 4), got {obs.shape}")
        if state.shape != (n, self.layers, self.hidden) or state.dtype != np.float32:
            raise ValueError(f"state must be float32 of shape (n, {self.layers}, {self.hidden})")
        if not state.flags.c_contiguous:
            raise ValueError("state must be C-contiguous")
        obs32 = torch.from_numpy(np.ascontiguousarray(obs, dtype=np.float32))
        if not torch.isfinite(obs32).all():
            raise ValueError("obs must be finite")
        gamma = torch.from_numpy(
            np.ascontiguousarray(np.broadcast_to(forgetting, (n,)), dtype=np.float32)
        ).reshape(n, 1)
        h_all = torch.from_numpy(state)
        delta = torch.empty(n, 2)
        for start in range(0, n, self.block):
            stop = min(n, start + self.block)
            self._block(obs32[start:stop], h_all[start:stop], gamma[start:stop], delta[start:stop])
        return delta.numpy().astype(np.float64)

    def _block(self, obs: torch.Tensor, h_all: torch.Tensor, gamma: torch.Tensor, out) -> None:
        b, hid = obs.shape[0], self.hidden
        x = self._x[:b]
        # features: [log kp, log ki, e, symlog int_e]
        torch.clamp_min(obs[:, :2], GAIN_FLOOR, out=x[:, :2]).log_()
        torch.clamp(obs[:, 2], -10.0, 10.0, out=x[:, 2])
        ie = obs[:, 3]
        torch.mul(torch.sign(ie), torch.log1p(ie.abs()), out=x[:, 3])
        gi, gh, h = self._gi[:b], self._gh[:b], self._h[:b]
        for layer, (w_ih, w_hh, b_i, b_hn) in enumerate(self._gru):
            h_prev = h_all[:, layer]  # view into the caller's state (strided rows)
            torch.mul(h_prev, gamma, out=h)
            # gi = [x W_ir + h W_hr + b_r | x W_iz + h W_hz + b_z | x W_in + b_in]
            torch.addmm(b_i, x, w_ih, out=gi)
            gi[:, : 2 * hid].addmm_(h, w_hh[:, : 2 * hid])
            torch.addmm(b_hn, h, w_hh[:, 2 * hid :], out=gh)
            rz = gi[:, : 2 * hid].sigmoid_()
            cand = gi[:, 2 * hid :].addcmul_(rz[:, :hid], gh).tanh_()
            # h' = n + z (h - n), written straight into the caller's state
            h.sub_(cand).mul_(rz[:, hid:]).add_(cand)
            h_prev.copy_(h)
            x = h_prev
        (w1, b1), (w2, b2), (w3, b3) = self._head
        a1, a2, mean = self._a1[:b], self._a2[:b], self._mean[:b]
        F.leaky_relu(torch.addmm(b1, x, w1, out=a1), LEAKY_SLOPE, inplace=True)
        F.leaky_relu(torch.addmm(b2, a1, w2, out=a2), LEAKY_SLOPE, inplace=True)
        torch.addmm(b3, a2, w3, out=mean)
        # relative change -> additive delta: max(k, floor) * expm1(clip(mean))
        tmp = self._tmp[:b]
        torch.clamp(mean, -MAX_LOG_STEP, MAX_LOG_STEP, out=tmp).expm1_()
        torch.mul(obs[:, :2].clamp_min(GAIN_FLOOR), tmp, out=out)

    def act(self, obs, state, forgetting=1.0) -> tuple[np.ndarray, np.ndarray]:
        """Same signature and results as ``agent.act`` for numpy inputs (state not modified)."""
        obs = np.asarray(obs, dtype=np.float64)
        new_state = np.array(state, dtype=np.float32, order="C", copy=True)
        return self.step_inplace(obs, new_state, forgetting), new_state
