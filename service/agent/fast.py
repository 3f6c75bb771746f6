"""Fast batched inference of the agent's actor: :meth:`Agent.act` for the tuner's hot path.

:class:`FastPolicy` wraps an :class:`~service.agent.Agent`'s weights and computes what
``agent.act`` computes, built for large batches on one or two CPU cores:

* the batch is processed in blocks of ``block`` loops whose intermediates (GEMM inputs,
  gates, head activations) live in buffers allocated once and reused, so they stay in
  the core's L2 cache and no call allocates;
* each GRU layer is GEMMs with the biases folded into the weights (the GEMM input is
  ``[x, 1, h, 1]``) into one gate buffer ``[a_r | a_z | a_in | a_hn]``, then one fused
  C kernel (``service/_gru.c``) for everything between the GEMMs: sigmoid, tanh, the
  update ``h' = n + z (gamma h - n)``, the write of ``h'`` into the caller's state, the
  next layer's GEMM input and, before the first layer, the input features. Torch's
  element-wise ops took as long as the GEMMs (about ten passes over memory per layer);
* ``precision="bfloat16"`` runs the GRU's GEMMs in bfloat16 (oneDNN, on AMX tiles where
  the CPU has them: 4-5x faster than float32 here) with float32 accumulation; the
  state, the gate arithmetic and the head stay float32. The error this adds is about
  1 % of the largest action and 0.02 of the hidden state per step, and it does not
  accumulate: closed-loop tuning results match float32 (``pitune evaluate --precision``
  measures it on the paper's experiments). Blocks of fewer than ``BF16_MIN_ROWS`` loops
  stay in float32 (faster there), and bfloat16 GEMMs run on a multiple of ``BF16_ROWS``
  rows so that oneDNN builds few kernels. ``"auto"`` picks bfloat16 when the CPU has
  native bfloat16 (AMX-BF16 or AVX512-BF16), float32 otherwise;
* the state is read from and written to the caller's ``(n, layers, hidden)`` float32
  array in place (:meth:`step_inplace`), with no transposes or copies of the whole batch;
* with ``workers=2`` a batch of at least ``parallel_min`` loops is split in halves, one
  stepped by a helper thread with its own buffers (torch ops and the kernel release the
  GIL), so a big batch uses two cores while small batches keep the single-thread
  latency. Each thread runs torch with one intra-op thread (the helper sets it; the
  caller's own setting, the daemon's ``inference_threads``, should be 1 too).

The C kernel is an optional extension (``pyproject.toml``): installed where no C
compiler is, pitune has no ``service.agent._gru``, and :class:`FastPolicy` says so once
in the log and steps with the agent's own torch ``act`` instead (same results; a step of
10,000 loops took 167 ms instead of 78 ms on a 2-core box: :data:`KERNEL` tells which path
runs).

The GRU equations (PyTorch's ``nn.GRU``, gates ordered r, z, n), with the paper's
forgetting factor ``gamma`` scaling the previous hidden state of every layer::

    h = gamma h_prev
    r = sigmoid(W_ir x + b_ir + W_hr h + b_hr)
    z = sigmoid(W_iz x + b_iz + W_hz h + b_hz)
    n = tanh(W_in x + b_in + r (W_hn h + b_hn))
    h' = (1 - z) n + z h = n + z (h - n)
"""

from __future__ import annotations

import logging
import weakref
from concurrent.futures import ThreadPoolExecutor
from functools import cache
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch.nn import functional as F

from service.agent.model import ERROR_CLIP, GAIN_FLOOR, MAX_LOG_STEP, Agent

try:
    from service.agent import _gru
except ImportError:  # installed without a C compiler: the extension is optional
    _gru = None
KERNEL = _gru is not None
"""Whether the fused C kernel is built; without it :class:`FastPolicy` runs ``agent.act``."""
log = logging.getLogger("pitune.agent")

Precision = Literal["auto", "float32", "bfloat16"]

LEAKY_SLOPE = 0.01
"""``nn.LeakyReLU``'s default negative slope (the actor's head uses the default)."""

BF16_ALIGN = 64
"""bfloat16 GEMM inputs are zero-padded to a multiple of this many columns (oneDNN/AMX)."""

BF16_ROWS = 128
"""bfloat16 GEMMs run on a multiple of this many rows (few shapes: oneDNN kernels cached)."""

BF16_MIN_ROWS = 128
"""Smaller blocks run in float32 (faster there: 0.3 vs 0.5 ms for 1-20 loops)."""

PARALLEL_MIN = 2048
"""Smallest batch that ``workers > 1`` splits across threads (smaller: caller only)."""

_BF16_CPU_FLAGS = {"amx_bf16", "avx512_bf16"}


@cache
def cpu_has_native_bf16(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """True when the CPU multiplies bfloat16 natively (AMX-BF16 or AVX512-BF16).

    Without it oneDNN emulates bfloat16 and the GEMMs are slower than float32.
    """
    try:
        text = cpuinfo.read_text()
    except OSError:  # not Linux: stay with float32
        return False
    for line in text.splitlines():
        if line.startswith("flags"):
            return bool(_BF16_CPU_FLAGS & set(line.split(":", 1)[1].split()))
    return False


def resolve_precision(precision: Precision) -> Literal["float32", "bfloat16"]:
    """``"auto"`` -> bfloat16 on a CPU with native bfloat16, else float32."""
    if precision == "auto":
        return "bfloat16" if cpu_has_native_bf16() else "float32"
    if precision not in ("float32", "bfloat16"):
        raise ValueError(f"precision must be auto, float32 or bfloat16, got {precision!r}")
    return precision


def _one_intraop_thread() -> None:
    # thread counts of OpenMP/MKL are per thread: a new thread starts with the defaults
    torch.set_num_threads(1)


class _Buffers:
    """One thread's preallocated intermediates for blocks of up to ``b`` loops."""

    def __init__(self, b: int, arith: dict, hid: int, widths: list[int]) -> None:
        e = torch.empty
        # per arithmetic and layer [x, 1, h, 1, 0...]: the GEMM inputs (biases folded
        # into the weights), and the gates [a_r | a_z | a_in | a_hn]
        self.xh, self.gates = {}, {}
        for bf16, layers in arith.items():
            dtype = torch.bfloat16 if bf16 else torch.float32
            self.xh[bf16] = []
            for k, width, _ in layers:
                buf = torch.zeros(b, width, dtype=dtype)  # stale rows must stay finite
                buf[:, k] = 1.0
                buf[:, k + 1 + hid] = 1.0
                self.xh[bf16].append(buf)
            self.gates[bf16] = e(b, 4 * hid, dtype=dtype)
        self.acts = []  # [deep h, 1], [a1, 1], [a2, 1]
        for w in [hid, *widths[:-1]]:
            buf = e(b, w + 1)
            buf[:, w] = 1.0
            self.acts.append(buf)
        self.gains, self.mean, self.tmp = e(b, 2), e(b, widths[-1]), e(b, widths[-1])
        self._views: dict[tuple[int, bool], tuple] = {}

    def views(self, b: int, bf16: bool) -> tuple:
        """The first rows of every buffer (cached: slicing costs ~2 us a view).

        bfloat16 GEMMs run on whole multiples of ``BF16_ROWS`` rows (the rest of the
        buffer's rows, stale but finite, are computed and ignored): oneDNN builds a
        kernel per shape, 3-4 ms each, which a batch of each new size would pay.
        """
        got = self._views.get((b, bf16))
        if got is None:
            if len(self._views) > 16:  # the full block and a few tails
                self._views.clear()
            m = min(-(-b // BF16_ROWS) * BF16_ROWS, len(self.gains)) if bf16 else b
            got = self._views[b, bf16] = (
                [buf[:m] for buf in self.xh[bf16]],
                self.gates[bf16][:m],
                [buf[:b] for buf in self.acts],
                self.gains[:b],
                self.mean[:b],
                self.tmp[:b],
            )
        return got


@cache
def _warn_no_kernel() -> None:
    log.warning(
        "the agent's C kernel (service.agent._gru) is not built (installed without a C "
        "compiler?): inference runs on torch (agent.act), about twice as slow at "
        "thousands of loops. Install a C compiler (Debian: gcc) and reinstall pitune for "
        "the fast path"
    )


def _gru_layers(gru: torch.nn.GRU, bf16: bool) -> list[tuple[int, int, list]]:
    """Per layer: input size k, GEMM input width, [(input columns, weight, gate columns)]."""
    hid, layers = gru.hidden_size, []
    for layer in range(gru.num_layers):
        w_ih = getattr(gru, f"weight_ih_l{layer}").detach().float().t()
        w_hh = getattr(gru, f"weight_hh_l{layer}").detach().float().t()
        b_ih = getattr(gru, f"bias_ih_l{layer}").detach().float()
        b_hh = getattr(gru, f"bias_hh_l{layer}").detach().float()
        k = w_ih.shape[0]
        # rows of [x, 1, h, 1] -> [a_r | a_z | a_in | a_hn]; the r and z biases add up,
        # the n gate keeps its hidden part apart for r (W_hn h + b_hn)
        width = k + 1 + hid + 1
        if bf16:  # zero rows up to whole AMX tiles: 106 -> 128 halves the GEMM's time
            width = -(-width // BF16_ALIGN) * BF16_ALIGN
        w = torch.zeros(width, 4 * hid)
        w[:k, : 3 * hid] = w_ih
        w[k, : 2 * hid] = b_ih[: 2 * hid] + b_hh[: 2 * hid]
        w[k, 2 * hid : 3 * hid] = b_ih[2 * hid :]
        w[k + 1 : k + 1 + hid, : 2 * hid] = w_hh[:, : 2 * hid]
        w[k + 1 : k + 1 + hid, 3 * hid :] = w_hh[:, 2 * hid :]
        w[k + 1 + hid, 3 * hid :] = b_hh[2 * hid :]
        if bf16:  # one GEMM: the zero blocks are cheap on AMX
            gemms = [(slice(None), w.to(torch.bfloat16), slice(None))]
        else:  # three GEMMs that skip the zero blocks (a third of the work)
            x1, h1 = slice(0, k + 1), slice(k + 1, None)
            gemms = [
                (slice(None), w[:, : 2 * hid], slice(0, 2 * hid)),
                (x1, w[x1, 2 * hid : 3 * hid], slice(2 * hid, 3 * hid)),
                (h1, w[h1, 3 * hid :], slice(3 * hid, None)),
            ]
        layers.append((k, width, [(i, m.contiguous(), o) for i, m, o in gemms]))
    return layers


class FastPolicy:
    """Allocation-free replacement of ``agent.act`` for numpy callers.

    ``precision``: ``"float32"`` equals ``agent.act`` to about 1e-6; ``"bfloat16"``
    and ``"auto"``: see the module docstring. ``workers``: threads stepping one batch
    of at least ``parallel_min`` loops (2 on a 2-core box; the helper threads are
    created once, idle between calls). Not safe for concurrent calls (the buffers are
    shared).
    """

    def __init__(
        self,
        agent: Agent,
        block: int = 1024,
        *,
        workers: int = 1,
        parallel_min: int = PARALLEL_MIN,
        precision: Precision = "float32",
    ) -> None:
        if workers < 1:
            raise ValueError("workers must be >= 1")
        self.agent = agent
        self.block = int(block)
        self.workers = int(workers)
        self.parallel_min = int(parallel_min)
        self.precision = resolve_precision(precision)
        self._pool = None
        cfg = agent.cfg
        self.layers, self.hidden = cfg.layers, cfg.hidden
        if not KERNEL:
            _warn_no_kernel()
            self.precision = "float32"  # agent.act's arithmetic
            return
        if cfg.hidden > _gru.MAX_HIDDEN:
            raise ValueError(f"hidden width {cfg.hidden} > {_gru.MAX_HIDDEN}, the kernel's limit")
        gru, head = agent.actor.gru, agent.actor.head
        self._bf16 = self.precision == "bfloat16"
        with torch.no_grad():
            # float32 always: blocks of fewer than BF16_MIN_ROWS loops are faster in it
            self._arith = {False: _gru_layers(gru, bf16=False)}
            if self._bf16:
                self._arith[True] = _gru_layers(gru, bf16=True)
            linears = [m for m in head if isinstance(m, torch.nn.Linear)]
            self._head = [
                torch.cat(
                    [m.weight.detach().float().t(), m.bias.detach().float()[None]]
                ).contiguous()
                for m in linears
            ]
        widths = [m.out_features for m in linears]
        self._bufs = [
            _Buffers(self.block, self._arith, self.hidden, widths) for _ in range(self.workers)
        ]
        if self.workers > 1:
            self._pool = ThreadPoolExecutor(
                self.workers - 1, "fastpolicy", initializer=_one_intraop_thread
            )
            weakref.finalize(self, self._pool.shutdown, wait=False)

    def close(self) -> None:
        """Stop the helper threads (they also stop when the policy is collected)."""
        if self._pool is not None:
            self._pool.shutdown(wait=False)
            self._pool = None

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
        if not KERNEL:
            delta, state[...] = self.agent.act(obs, state, forgetting)
            return delta
        obs32 = torch.from_numpy(np.ascontiguousarray(obs, dtype=np.float32))
        if not torch.isfinite(obs32).all():
            raise ValueError("obs must be finite")
        gamma = torch.from_numpy(
            np.ascontiguousarray(np.broadcast_to(forgetting, (n,)), dtype=np.float32)
        )
        h_all = torch.from_numpy(state)
        delta = torch.empty(n, 2)
        args = (obs32, h_all, gamma, delta)
        if self._pool is None or n < self.parallel_min:
            self._run(self._bufs[0], 0, n, *args)
        else:
            # contiguous shares of whole blocks; the caller steps the first one
            blocks = -(-n // self.block)
            cuts = [
                min(n, (blocks * i // self.workers) * self.block) for i in range(1 + self.workers)
            ]
            futures = [
                self._pool.submit(self._run_in_helper, self._bufs[i], cuts[i], cuts[i + 1], *args)
                for i in range(1, self.workers)
            ]
            try:
                self._run(self._bufs[0], cuts[0], cuts[1], *args)
            finally:
                for future in futures:
                    future.result()
        return delta.numpy().astype(np.float64)

    @torch.inference_mode()
    def _run_in_helper(self, *args) -> None:
        self._run(*args)  # inference mode is per thread

    def _run(self, bufs: _Buffers, start: int, stop: int, obs, h_all, gamma, delta) -> None:
        for lo in range(start, stop, self.block):
            hi = min(stop, lo + self.block)
            self._block(bufs, obs[lo:hi], h_all[lo:hi], gamma[lo:hi], delta[lo:hi])

    def _block(self, bufs: _Buffers, obs, h_all, gamma, out) -> None:
        b, hid = obs.shape[0], self.hidden
        bf16 = self._bf16 and b >= BF16_MIN_ROWS
        xhs, gates, acts, gains, mean, tmp = bufs.views(b, bf16)
        g_ptr, hs = gamma.data_ptr(), h_all.stride(0)
        x0 = xhs[0]
        _gru.features(
            b, obs.data_ptr(), gains.data_ptr(), x0.data_ptr(), x0.stride(0), bf16,
            GAIN_FLOOR, ERROR_CLIP,
        )  # fmt: skip
        for layer, (k, _, gemms) in enumerate(self._arith[bf16]):
            xh = xhs[layer]  # [x, 1, h, 1]
            h_ptr = h_all[:, layer].data_ptr()  # the caller's state (strided rows)
            _gru.pre(b, hid, h_ptr, hs, g_ptr, xh[:, k + 1].data_ptr(), xh.stride(0), bf16)
            for cols, w, gate_cols in gemms:
                torch.mm(xh[:, cols], w, out=gates[:, gate_cols])
            if layer + 1 < self.layers:  # h' -> the next layer's GEMM input
                nxt = xhs[layer + 1]
                to_next, next_stride, to_head, head_stride = nxt.data_ptr(), nxt.stride(0), 0, 0
            else:  # h' -> the head's float32 input
                to_next, next_stride = 0, 0
                to_head, head_stride = acts[0].data_ptr(), acts[0].stride(0)
            _gru.post(
                b, hid, gates.data_ptr(), gates.stride(0), bf16, h_ptr, hs, g_ptr,
                to_next, next_stride, to_head, head_stride,
            )  # fmt: skip
        for i, w in enumerate(self._head[:-1]):
            F.leaky_relu_(torch.mm(acts[i], w, out=acts[i + 1][:, :-1]), LEAKY_SLOPE)
        torch.mm(acts[-1], self._head[-1], out=mean)
        # relative change -> additive delta: max(k, floor) * expm1(clip(mean))
        torch.clamp(mean, -MAX_LOG_STEP, MAX_LOG_STEP, out=tmp).expm1_()
        torch.mul(gains, tmp, out=out)

    @property
    def meta(self) -> dict:
        return self.agent.meta

    def initial_state(self, n: int) -> np.ndarray:
        return self.agent.initial_state(n)

    def act(self, obs, state, forgetting=1.0) -> tuple[np.ndarray, np.ndarray]:
        """Same signature and results as ``agent.act`` for numpy inputs (state not modified)."""
        obs = np.asarray(obs, dtype=np.float64)
        new_state = np.array(state, dtype=np.float32, order="C", copy=True)
        return self.step_inplace(obs, new_state, forgetting), new_state
