"""The nonlinear two-tank cascade of the paper's section 5.4 (after Lawrence et al. 2022).

Internal units are the paper's: length in dm, time in minutes, volume in litres
(1 L = 1 dm^3), so g = 9.81 m/s^2 = 353,160 dm/min^2. The interface is in the units a
DCS would show: level in cm, flow in L/min, time in seconds.

States and equations (tau_p, tau_in, tau_out, tau_m = 0.1, 0.1, 0.1, 0.2 min)::

    tau_p   dp/dt     = p_bar - p                              pump speed, %
    tau_in  df_in/dt  = f_max p/100 - f_in                     inflow, L/min
    tau_out df_out/dt = pi r_pipe^2 f_c sqrt(2 g l) - f_out    outflow, L/min
    pi r_tank^2 dl/dt = f_in - f_out                           level, dm, clipped to [0, H]
    tau_m   dm/dt     = l - m                                  measured (filtered) level, dm

The inner flow loop ``p_bar = PI_flow(f_in_sp - f_in)`` is part of the plant: its input
is the flow setpoint (the level controller's output). Its gains are fixed at
kp = 1.25 %/(L/min), ki = 8.33 %/(L/min min): SIMC for the pump-inflow path
0.8 %^-1 L/min / (0.1 s + 1)^2, approximated by the half rule as 0.8/(0.15 s + 1)
exp(-0.05 s), with tau_c = 0.1 min. That makes the flow loop settle within about half
a minute without overshoot, well inside the level dynamics (time constant near a
minute), which is what a cascade needs.

Around a 55 cm level the outflow is about 59 L/min, and a step of the flow setpoint
moves the level like K exp(-theta s)/(tau s + 1) with K 1.85-1.95 cm/(L/min), tau
48-52 s and theta 18.5 s (least-squares fits of steps of -1, +1 and +5 L/min: the tank
is nonlinear; linearised, K = 2 l / f_out = 1.86 and the tank's own lag 51 s, the flow
loop and the level filter adding the dead time); the demo's rounded reference model
``plant_sim.scenario.TANK_FIT`` is 1.9 exp(-15 s)/(47 s + 1), the paper's approximation
1.7 exp(-13 s)/(55 s + 1). The continuous states are integrated with classical RK4 at
``substeps`` per DCS scan, with the flow PI sampled at the same rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from plant_sim.pi import PIBatch

G_DM_PER_MIN2 = 9.81 * 10 * 3600.0  # 9.81 m/s^2 in dm/min^2 = 353,160


MAX_SUBSTEP_S = 2.5
"""Longest integration substep (RK4 and the inner flow PI), in seconds: the inner lags are
6-12 s. A scan's 4 substeps (the default, unchanged up to a 10 s scan) grew with the
scan: at a 60 s scan the level settled at 31 cm for the flow that holds 67 cm."""


@dataclass(frozen=True)
class TwoTankParams:
    """Parameters of the paper's Table 3 (dm, min, L)."""

    r_tank: float = 1.2065
    r_pipe: float = 0.125
    f_max: float = 80.0
    f_c: float = 0.61
    tau_p: float = 0.1
    tau_in: float = 0.1
    tau_out: float = 0.1
    tau_m: float = 0.2
    height: float = 12.192
    g: float = G_DM_PER_MIN2
    flow_kp: float = 1.25
    flow_ki: float = 8.33

    @property
    def area(self) -> float:
        return np.pi * self.r_tank**2

    def outflow(self, level_dm: ArrayLike) -> np.ndarray:
        """Bernoulli outflow (L/min) at a level in dm."""
        level = np.maximum(np.asarray(level_dm, dtype=np.float64), 0.0)
        return np.pi * self.r_pipe**2 * self.f_c * np.sqrt(2.0 * self.g * level)


class TwoTankBatch:
    """N two-tank plants with their inner flow loops; input flow setpoint, output level.

    Parameters
    ----------
    n:
        Number of plants.
    level_cm:
        Initial steady-state level (cm).
    dt:
        DCS scan interval in seconds: each :meth:`step` holds the flow setpoint this long.
    substeps:
        RK4 steps (and flow-PI samples) per scan; None: 4, or more where a substep would
        be longer than :data:`MAX_SUBSTEP_S`.
    noise_cm:
        Half-width of uniform measurement noise on the reported level, cm (the paper's
        "+-1 cm").
    """

    def __init__(
        self,
        n: int = 1,
        *,
        level_cm: ArrayLike = 55.0,
        dt: float = 1.0,
        substeps: int | None = None,
        noise_cm: float = 0.0,
        params: TwoTankParams | None = None,
        seed: int | np.random.Generator | None = None,
    ) -> None:
        self.n = n
        self.dt = float(dt)
        self.substeps = int(substeps or max(4, math.ceil(self.dt / MAX_SUBSTEP_S)))
        self.p = params or TwoTankParams()
        self.h = self.dt / 60.0 / self.substeps  # minutes
        self.noise_cm = float(noise_cm)
        self.rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        self.flow_pi = PIBatch(
            self.p.flow_kp, self.p.flow_ki, dt=self.h, n=n, u_min=0.0, u_max=100.0
        )
        self.steady_state(level_cm)

    def steady_state(self, level_cm: ArrayLike) -> None:
        """Put every tank in equilibrium at ``level_cm`` (inflow equals outflow)."""
        level = np.broadcast_to(np.asarray(level_cm, dtype=np.float64) / 10.0, (self.n,)).copy()
        flow = self.p.outflow(level)
        pump = 100.0 * flow / self.p.f_max
        # state columns: pump speed, inflow, outflow, level, measured level
        self.x = np.stack([pump, flow, flow, level, level], axis=1)
        self.flow_pi.initialise(pump)

    def equilibrium_flow(self, level_cm: ArrayLike) -> np.ndarray:
        """Inflow (L/min) that holds the level at ``level_cm``."""
        return self.p.outflow(np.asarray(level_cm, dtype=np.float64) / 10.0)

    @property
    def level_cm(self) -> np.ndarray:
        """True tank level, cm."""
        return self.x[:, 3] * 10.0

    @property
    def inflow(self) -> np.ndarray:
        return self.x[:, 1]

    @property
    def outflow(self) -> np.ndarray:
        return self.x[:, 2]

    def measure(self) -> np.ndarray:
        """Measured (filtered) level in cm, plus measurement noise if configured."""
        m = self.x[:, 4] * 10.0
        if self.noise_cm:
            m = m + self.rng.uniform(-self.noise_cm, self.noise_cm, self.n)
        return m

    def _deriv(self, x: np.ndarray, p_bar: np.ndarray) -> np.ndarray:
        p = self.p
        pump, f_in, f_out, level, meas = x.T
        return np.stack(
            [
                (p_bar - pump) / p.tau_p,
                (p.f_max * np.clip(pump, 0.0, 100.0) / 100.0 - f_in) / p.tau_in,
                (p.outflow(level) - f_out) / p.tau_out,
                (f_in - f_out) / p.area,
                (level - meas) / p.tau_m,
            ],
            axis=1,
        )

    def step(self, flow_sp: ArrayLike) -> np.ndarray:
        """Hold the flow setpoint (L/min) for one scan; return the noise-free level reading (cm)."""
        flow_sp = np.broadcast_to(np.asarray(flow_sp, dtype=np.float64), (self.n,))
        h = self.h
        for _ in range(self.substeps):
            p_bar = self.flow_pi.step(flow_sp - self.x[:, 1])
            k1 = self._deriv(self.x, p_bar)
            k2 = self._deriv(self.x + 0.5 * h * k1, p_bar)
            k3 = self._deriv(self.x + 0.5 * h * k2, p_bar)
            k4 = self._deriv(self.x + h * k3, p_bar)
            self.x = self.x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
            self.x[:, 3] = np.clip(self.x[:, 3], 0.0, self.p.height)
        return self.x[:, 4] * 10.0
