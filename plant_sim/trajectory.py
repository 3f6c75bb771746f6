"""Trajectory logs of simulated loops: CSV on disk, tracking metrics, and the PNG plot.

A log is one CSV file per loop with the header ``t,sp,pv,pv_true,target,kp,ki,op``
(seconds and the loop's engineering units; ``pv`` as measured, ``pv_true`` without the
measurement noise), one row per DCS scan. :func:`tracking_mse` is the number the demo
and the end-to-end tests compare: the mean squared deviation of the true PV from the
target trajectory over the last few setpoint changes, i.e. once the tuner has had time
to act. The true PV, as the paper's tracking error and ``pitune evaluate``'s two-tank
figures: the measured one adds the noise's variance (N^2/3 for noise +-N), which no
tuning removes (at +-1 cm 0.33 cm^2: 13 times the tuned loop's 0.025 cm^2 in
``pitune demo --noise 1``).
"""

from __future__ import annotations

import csv
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from plant_sim.scenario import Scan

COLUMNS = ("t", "sp", "pv", "pv_true", "target", "kp", "ki", "op")
BEFORE_PV_TRUE = tuple(c for c in COLUMNS if c != "pv_true")
"""A log's header before session 41, which logged the measured PV only: read with
``pv_true`` = ``pv`` (its tracking MSE then includes the noise, as it did then)."""


class TrajectoryWriter:
    """Appends scans to a CSV log; flushes every ``flush_every`` rows so a killed run keeps them."""

    def __init__(self, path: str | Path, flush_every: int = 50) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: TextIO = self.path.open("w", newline="")
        self._csv = csv.writer(self._file)
        self._csv.writerow(COLUMNS)
        self._flush_every = flush_every
        self._pending = 0

    def write(self, scan: Scan) -> None:
        self._csv.writerow([repr(float(getattr(scan, c))) for c in COLUMNS])
        self._pending += 1
        if self._pending >= self._flush_every:
            self._file.flush()
            self._pending = 0

    def close(self) -> None:
        self._file.close()


@dataclass(frozen=True)
class Trajectory:
    """A loaded log: one float array per column."""

    t: np.ndarray
    sp: np.ndarray
    pv: np.ndarray
    pv_true: np.ndarray
    target: np.ndarray
    kp: np.ndarray
    ki: np.ndarray
    op: np.ndarray

    @classmethod
    def from_scans(cls, scans: list[Scan]) -> Trajectory:
        rows = np.array([[getattr(s, c) for c in COLUMNS] for s in scans], dtype=np.float64)
        return cls(*rows.T)

    def setpoint_changes(self) -> np.ndarray:
        """Times at which the setpoint stepped."""
        return self.t[1:][np.diff(self.sp) != 0]

    def window(self, last_changes: int) -> np.ndarray:
        """Mask of the samples from the ``last_changes``-th last setpoint change to the end."""
        changes = self.setpoint_changes()
        if len(changes) < last_changes:
            raise ValueError(
                f"log has {len(changes)} setpoint changes, fewer than the {last_changes} asked"
            )
        return self.t >= changes[-last_changes]

    def tracking_error(self) -> np.ndarray:
        """The true PV's deviation from the target, per scan."""
        return self.pv_true - self.target

    def tracking_mse(self, last_changes: int = 2) -> float:
        """Mean squared :meth:`tracking_error` over the last setpoint changes."""
        return float(np.mean(self.tracking_error()[self.window(last_changes)] ** 2))

    def __len__(self) -> int:
        return len(self.t)


def read_log(path: str | Path) -> Trajectory:
    """Load a CSV log written by :class:`TrajectoryWriter` (a partial last line is dropped)."""
    with Path(path).open(newline="") as f:
        reader = csv.reader(f)
        header = next(reader, None)
        if header is None:
            raise ValueError(f"{path}: empty, not a trajectory log")
        if tuple(header) not in (COLUMNS, BEFORE_PV_TRUE):
            raise ValueError(f"{path}: header {header} is not {list(COLUMNS)}")
        rows = [r for r in reader if len(r) == len(header)]
    try:
        data = np.array(rows, dtype=np.float64).reshape(-1, len(header))
    except ValueError as exc:
        raise ValueError(f"{path}: not a trajectory log: {exc}") from None
    columns = dict(zip(header, data.T, strict=True))
    columns.setdefault("pv_true", columns["pv"])
    return Trajectory(*(columns[c] for c in COLUMNS))


def plot(
    runs: Mapping[str, Trajectory],
    out: str | Path,
    *,
    title: str = "",
    units: str = "",
    gain_units: str = "",
) -> Path:
    """PV vs setpoint vs target (top) and kp, ki (bottom) of one or more runs, as a PNG.

    The first run's setpoint and target are drawn (runs are meant to share a schedule).
    ``units``: the PV's; ``gain_units``: kp's (output per PV unit; ki's is that per s).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = next(iter(runs.values()))
    minutes = 60.0
    fig, (ax_pv, ax_kp) = plt.subplots(2, 1, figsize=(10, 7), sharex=True, height_ratios=(3, 2))
    ax_pv.step(first.t / minutes, first.sp, where="post", color="0.6", lw=1, label="setpoint")
    ax_pv.plot(first.t / minutes, first.target, "k--", lw=1, label="target")
    ax_ki = ax_kp.twinx()
    for i, (label, run) in enumerate(runs.items()):
        color = f"C{i}"
        ax_pv.plot(run.t / minutes, run.pv, color=color, lw=1, label=f"PV, {label}")
        ax_kp.plot(run.t / minutes, run.kp, color=color, lw=1.5, label=f"kp, {label}")
        ax_ki.plot(run.t / minutes, run.ki, color=color, lw=1.5, ls=":", label=f"ki, {label}")
    ax_pv.set_ylabel(f"PV {units}".strip())
    ax_pv.legend(loc="upper right", fontsize=8)
    ax_pv.set_title(title)
    ax_kp.set_ylabel(f"kp, {gain_units} (solid)" if gain_units else "kp (solid)")
    ax_ki.set_ylabel(f"ki, {gain_units}/s (dotted)" if gain_units else "ki, kp/s (dotted)")
    ax_kp.set_xlabel("simulated time, min")
    handles = ax_kp.get_legend_handles_labels()
    more = ax_ki.get_legend_handles_labels()
    ax_kp.legend(handles[0] + more[0], handles[1] + more[1], loc="center right", fontsize=8)
    for ax in (ax_pv, ax_kp):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
