"""Regenerate the console's screenshots in docs/ under a running simulation.

    python -m service.daemon.console.screenshots [--out docs] [--seconds 40]

Starts a tuner daemon in this process (the shipped agent, a fresh database in a
temporary directory, the admin API and console on a free loopback port, Zenoh on
loopback), registers a small simulated plant (:class:`SimPlant`: FOPTD loops under PI
control, setpoint steps, the gains the tuner publishes applied in ``auto``), lets it
run, then opens the console in headless Chromium (Debian's ``/usr/bin/chromium``
driven by Playwright for Python) and writes ``console-overview.png``,
``console-loop.png`` and ``console-tuner.png``.

:func:`serve` and :class:`SimPlant` are also what the browser tests use.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import queue
import random
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run",
]  # fmt: skip


@dataclass
class Daemon:
    """A tuner daemon served in this process (see :func:`serve`)."""

    url: str
    app: object
    tuner: object
    settings: object


def with_console(app) -> object:
    """The app with the console's router (once: the daemon may include it already)."""
    from service.daemon import console

    if not any(getattr(r, "path", "").startswith("/ui") for r in app.routes):
        app.include_router(console.router)
    return app


@contextlib.contextmanager
def serve(settings, agent=None, host: str = "127.0.0.1") -> Iterator[Daemon]:
    """The daemon (``create_app``: tuner, admin API, console) under uvicorn on a free
    port, in a thread; the tuner's ring of recent samples attached if the daemon does
    not wire one itself. Stops it (and the tuner) on exit."""
    import uvicorn

    from service.daemon.api import create_app
    from service.daemon.recent import attach
    from service.wire.session import free_port

    app = with_console(create_app(settings, agent=agent))
    port = free_port()
    config = uvicorn.Config(
        app, host=host, port=port, lifespan="on", timeout_graceful_shutdown=2,
        access_log=False, log_config=None, log_level=None,  # the process's logging untouched
    )  # fmt: skip
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, name="console-uvicorn", daemon=True)
    thread.start()
    deadline = time.monotonic() + 60.0
    while not server.started:
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the daemon did not start")
        time.sleep(0.02)
    tuner = app.state.tuner
    attach(tuner)
    try:
        yield Daemon(f"http://{host}:{port}", app, tuner, settings)
    finally:
        server.should_exit = True
        thread.join(timeout=30.0)


@dataclass
class SimLoop:
    """An FOPTD process under a velocity-form PI (engineering units, plant seconds)."""

    id: str
    k: float = 1.5
    tau: float = 40.0
    theta: float = 5.0
    kp: float = 0.3
    ki: float = 0.005
    sp_low: float = 40.0
    sp_high: float = 55.0
    sp_period: float = 300.0
    noise: float = 0.05
    pv: float = field(default=math.nan)
    op: float = 30.0
    sp: float = math.nan
    e_prev: float = 0.0
    seq: int = 0
    mode: str = "auto"
    _buffer: list[float] = field(default_factory=list)

    def body(self, dt: float, **extra: object) -> dict:
        """Its registration (``POST /loops``), with a model hint near the truth."""
        return {
            "id": self.id, "kp": self.kp, "ki": self.ki, "sample_period_s": dt,
            "scaling": {"k_hat": self.k * 1.1, "tau_hat": self.tau * 0.9, "pv_scale": 10.0},
            **extra,
        }  # fmt: skip

    def step(self, t: float, dt: float, rng: random.Random) -> dict:
        if math.isnan(self.pv):
            self.pv = self.sp_low
            self.op = self.sp_low / self.k
            self._buffer = [self.op] * max(1, round(self.theta / dt))
        phase = int(t // self.sp_period) % 2
        self.sp = self.sp_high if phase else self.sp_low
        e = self.sp - self.pv
        self.op = min(100.0, max(0.0, self.op + self.kp * (e - self.e_prev) + self.ki * dt * e))
        self.e_prev = e
        self._buffer.append(self.op)
        u = self._buffer.pop(0)
        self.pv += dt / self.tau * (self.k * u - self.pv)
        pv = self.pv + rng.gauss(0.0, self.noise)
        return {"t": t, "sp": self.sp, "pv": pv, "op": self.op, "kp": self.kp, "ki": self.ki}


class SimPlant:
    """Simulated loops behind a gateway on the Zenoh bus: a sample per loop and period
    (``dt`` plant seconds every ``dt / speed`` wall seconds), the tuner's gains applied
    when their mode is auto (and their seq new)."""

    def __init__(self, settings, loops: list[SimLoop], dt: float = 1.0, speed: float = 20.0,
                 seed: int = 0) -> None:  # fmt: skip
        import zenoh

        from service.wire.session import session_config

        self.keys = settings.keys
        self.loops = {loop.id: loop for loop in loops}
        self.dt, self.speed = dt, speed
        self.rng = random.Random(seed)
        self.t = 0.0
        self.applied: queue.SimpleQueue = queue.SimpleQueue()
        """(loop id, seq, kp, ki) of every gains message applied."""
        self._gains: queue.SimpleQueue = queue.SimpleQueue()
        self.session = zenoh.open(session_config(mode="peer", connect=settings.zenoh_listen))
        self._sub = self.session.declare_subscriber(
            self.keys.all_gains, lambda s: self._gains.put(s.payload.to_bytes())
        )
        self._stop = threading.Event()
        self._holding = threading.Event()
        self._held = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> SimPlant:
        self._thread = threading.Thread(target=self._run, name="sim-plant", daemon=True)
        self._thread.start()
        return self

    def add(self, loop: SimLoop) -> None:
        self.loops[loop.id] = loop

    @contextlib.contextmanager
    def held(self, timeout: float = 30.0) -> Iterator[float]:
        """Inside it the plant sends no sample (its time stands still) but still applies
        gains: no agent step nor verdict, which samples drive, changes a loop meanwhile, so
        a test's operator decides on the proposal the page shows, not on one the next
        sample replaced. Yields the time of the last sample sent."""
        self._held.clear()
        self._holding.set()
        try:
            if not self._held.wait(timeout):
                raise TimeoutError(f"the plant did not stop within {timeout} s")
            yield self.t
        finally:
            self._holding.clear()

    def _apply_gains(self) -> None:
        while True:
            try:
                message = json.loads(self._gains.get_nowait())
            except queue.Empty:
                return
            loop = self.loops.get(message.get("loop_id"))
            if loop is None or message.get("mode") != "auto" or message["seq"] <= loop.seq:
                continue
            loop.seq, loop.kp, loop.ki = message["seq"], message["kp"], message["ki"]
            self.applied.put((loop.id, loop.seq, loop.kp, loop.ki))

    def _run(self) -> None:
        period = self.dt / self.speed
        next_at = time.monotonic()
        while not self._stop.is_set():
            self._apply_gains()
            if self._holding.is_set():
                self._held.set()
            else:
                self.t += self.dt
                for loop in list(self.loops.values()):
                    sample = loop.step(self.t, self.dt, self.rng)
                    self.session.put(self.keys.sample(loop.id), json.dumps(sample).encode())
            next_at += period
            self._stop.wait(max(0.0, next_at - time.monotonic()))

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._sub.undeclare()
        self.session.close()


def demo_loops(n: int = 12, seed: int = 1) -> list[SimLoop]:
    """A small plant: level, flow, temperature and pressure loops of varied dynamics."""
    rng = random.Random(seed)
    kinds = [("LIC", 1.2, 30.0, 4.0), ("FIC", 0.8, 8.0, 1.0), ("TIC", 2.0, 90.0, 12.0),
             ("PIC", 1.0, 15.0, 2.0)]  # fmt: skip
    loops = []
    for i in range(n):
        tag, k, tau, theta = kinds[i % len(kinds)]
        f = rng.uniform(0.7, 1.4)
        loops.append(
            SimLoop(
                id=f"{tag}-{101 + i}", k=k * f, tau=tau * f, theta=theta,
                kp=0.25 / (k * f) * rng.uniform(0.5, 1.5), ki=0.25 / (k * f) / (tau * f),
                sp_low=40.0 + 5 * (i % 3), sp_high=50.0 + 5 * (i % 3),
                sp_period=rng.choice([120.0, 180.0, 240.0]),
            )
        )  # fmt: skip
    return loops


def _wait(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(what)
        time.sleep(0.1)


def take(out: Path, seconds: float, loops: int, speed: float) -> list[Path]:
    import httpx
    from playwright.sync_api import sync_playwright

    from service.daemon.settings import load_settings
    from service.wire.session import free_port

    out.mkdir(parents=True, exist_ok=True)
    token = "screenshot-token"
    with tempfile.TemporaryDirectory() as tmp:
        settings = load_settings(
            zenoh_listen=[f"tcp/127.0.0.1:{free_port()}"], db_path=Path(tmp) / "pitune.db",
            instance_id="screenshots", api_token=token, snapshot_interval_s=3600.0,
        )  # fmt: skip
        with serve(settings) as daemon:
            plant_loops = demo_loops(loops)
            headers = {"Authorization": f"Bearer {token}"}
            bodies = [
                loop.body(1.0, gateway="unit-1" if i % 2 else None)
                for i, loop in enumerate(plant_loops)
            ]
            r = httpx.post(f"{daemon.url}/loops/bulk", json=bodies, headers=headers, timeout=30)
            r.raise_for_status()
            httpx.patch(f"{daemon.url}/loops/{plant_loops[3].id}", json={"mode": "advisory"},
                        headers=headers).raise_for_status()  # fmt: skip
            plant = SimPlant(settings, plant_loops, dt=1.0, speed=speed).start()
            try:
                tuner = daemon.tuner
                _wait(lambda: tuner.metrics.value("pitune_updates_published_total", mode="auto")
                      >= loops, seconds * 4, "gains updates")  # fmt: skip
                time.sleep(seconds)  # the trends fill (a screenshot, not a test)
                with sync_playwright() as pw:
                    browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                    # bypass_csp: Playwright's wait_for_function evaluates strings
                    page = browser.new_page(viewport={"width": 1500, "height": 900},
                                            bypass_csp=True)  # fmt: skip
                    page.goto(f"{daemon.url}/ui/login")
                    page.fill("#token", token)
                    page.fill("#name", "operator")
                    page.click("#login-submit")
                    page.wait_for_selector("#loops tbody tr[data-id]")
                    shots = [out / "console-overview.png"]
                    page.screenshot(path=str(shots[0]), full_page=True)
                    page.goto(f"{daemon.url}/ui/loops/{plant_loops[0].id}")
                    page.wait_for_function(
                        "document.getElementById('trend-count').dataset.points > 100"
                    )
                    page.wait_for_selector("#history tbody tr")
                    shots.append(out / "console-loop.png")
                    page.screenshot(path=str(shots[1]), full_page=True)
                    page.goto(f"{daemon.url}/ui/tuner")
                    page.wait_for_selector("body[data-loaded='1']")
                    page.wait_for_selector("#hold-history tbody tr")
                    page.wait_for_function(
                        "/\\d \\/s/.test(document.getElementById('t-traffic').innerText)"
                    )
                    shots.append(out / "console-tuner.png")
                    page.screenshot(path=str(shots[2]), full_page=True)
                    browser.close()
            finally:
                plant.close()
    return shots


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("docs"))
    parser.add_argument("--seconds", type=float, default=30.0, help="wall seconds of simulation")
    parser.add_argument("--loops", type=int, default=12)
    parser.add_argument("--speed", type=float, default=20.0, help="plant seconds per wall second")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    for path in take(args.out, args.seconds, args.loops, args.speed):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
