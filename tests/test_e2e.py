"""End to end: the tuner and the plant simulator as separate OS processes, real Zenoh on
loopback, real HTTP. Each scenario runs the two-tank loop at a high speed factor; every
process is reaped whatever happens (:class:`service.procs.Stack`). The scenarios that
run for tens of seconds are marked ``slow`` (``-m "not slow"`` leaves them out)."""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import subprocess
import sys
import threading
import time

import httpx
import numpy as np
import pytest
import zenoh

from plant_sim.config import DEFAULT_LOOPS, Simulation, untuned_baseline
from plant_sim.trajectory import read_log
from service.agent import DEFAULT_WEIGHTS
from service.procs import ROOT, Stack
from service.wire.protocol import GainsMessage, Keys, UpdateReason
from tests.sockets import LOOPBACK, listening
from tests.tuner_support import snapshot_of

SPEED = 100.0
"""Simulated seconds per wall second: one RL step (165 s of plant time) every 1.65 s."""
LOOP = "tank1"
REGISTERED = (0.05 * 0.5 / 1.2, 0.05 * 0.5 / 1.2 / 60.0)
"""The registered (untuned) gains: the paper's initial tuning through the hint."""

pytestmark = pytest.mark.timeout(240)


def auth(stack: Stack) -> dict[str, str]:
    return {"Authorization": f"Bearer {stack.token}"}


def view(stack: Stack) -> dict:
    response = httpx.get(f"{stack.api}/loops/{LOOP}", timeout=5.0)
    response.raise_for_status()
    return response.json()


def wait_for(condition, what: str, timeout: float = 60.0, every: float = 0.2):
    """Poll ``condition`` until it returns something truthy; fail after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if result := condition():
            return result
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def wait_view(stack: Stack, predicate, what: str, timeout: float = 60.0) -> dict:
    """The loop's view once ``predicate(view)`` holds (not registered yet counts as not)."""

    def check():
        response = httpx.get(f"{stack.api}/loops/{LOOP}", timeout=5.0)
        return response.is_success and predicate(v := response.json()) and v

    return wait_for(check, what, timeout)


def gains_listener(stack: Stack):
    """A Zenoh peer of the tuner collecting the gains messages it publishes."""
    config = zenoh.Config()
    config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", json.dumps([stack.zenoh]))
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    inbox: queue.SimpleQueue = queue.SimpleQueue()
    sub = session.declare_subscriber(
        Keys().all_gains,
        lambda s: inbox.put(GainsMessage.model_validate_json(s.payload.to_bytes())),
    )
    return session, sub, inbox


def drain(inbox: queue.SimpleQueue) -> list[GainsMessage]:
    out = []
    while not inbox.empty():
        out.append(inbox.get())
    return out


def plant_log(stack: Stack, name: str = LOOP):
    return read_log(stack.log_dir / f"{name}.csv")


@pytest.mark.skipif(
    not DEFAULT_WEIGHTS.exists(), reason=f"trained agent weights absent ({DEFAULT_WEIGHTS})"
)
@pytest.mark.slow
def test_demo_tunes_the_two_tank_loop_at_least_3x_better_than_untuned(tmp_path):
    """`pitune demo --keep` (tuner + plant subprocesses, REST registration, Zenoh) vs the
    same seed untuned; the MSE is recomputed here from the plant's own log. With --keep the
    console stays up after the report until the demo is interrupted."""
    out = tmp_path / "demo"
    argv = [sys.executable, "-m", "service.cli", "demo", "--out", str(out), "--speed", "150",
            "--workdir", str(tmp_path / "work"), "--keep"]  # fmt: skip
    started = time.monotonic()
    demo = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)  # fmt: skip
    try:
        stdout, console, wall = _until_kept(demo, started)
        page = httpx.get(console, timeout=10)  # the console outlives the run
        assert page.status_code == 200 and "pitune" in page.text
        demo.send_signal(signal.SIGINT)
        assert demo.wait(timeout=30) == 0, "".join(stdout)[-2000:] + demo.stderr.read()
    finally:  # never leave a kept stack behind a failed assertion: its whole group goes
        if demo.poll() is None:
            os.killpg(demo.pid, signal.SIGKILL)
            demo.wait()
    with pytest.raises(httpx.TransportError):  # and is gone after the interrupt
        httpx.get(console, timeout=2)
    assert "level-target RMS" in "".join(stdout)  # the progress line
    tuned = read_log(out / "tank1.csv")
    untuned = untuned_baseline(DEFAULT_LOOPS, Simulation(duration=3600.0))["tank1"]
    np.testing.assert_array_equal(tuned.sp, untuned.sp)
    mse_tuned, mse_untuned = tuned.tracking_mse(2), untuned.tracking_mse(2)
    assert mse_untuned >= 3 * mse_tuned, (mse_tuned, mse_untuned)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["mse_tuned_cm2"] == pytest.approx(mse_tuned)
    assert summary["mse_untuned_cm2"] == pytest.approx(mse_untuned)
    assert summary["gain_updates"] >= 15  # one per 165 s of plant time
    assert (out / "two_tank.png").read_bytes()[:4] == b"\x89PNG"
    assert wall < 180


def _until_kept(demo: subprocess.Popen, started: float) -> tuple[list[str], str, float]:
    """The demo's output up to its --keep line (the report is written by then), the
    console's address it printed, and the wall time to that line."""
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in demo.stdout], daemon=True).start()
    stdout, console = [], ""
    while not any(x.startswith("--keep:") for x in stdout):
        try:
            stdout.append(lines.get(timeout=max(0.0, started + 200 - time.monotonic())))
        except queue.Empty:
            pytest.fail("no --keep line:\n" + "".join(stdout)[-2000:])
        if stdout[-1].startswith("operator console: "):
            console = stdout[-1].split()[2]
    return stdout, console, time.monotonic() - started


@pytest.mark.slow
def test_tuner_sigkill_and_restart_resumes_the_loop_while_the_plant_runs_on(tmp_path):
    with Stack(tmp_path, speed=SPEED) as stack:
        tuner = stack.start_tuner("--snapshot-interval", "0.5")
        session, sub, inbox = gains_listener(stack)
        try:
            stack.start_plant("--tank", LOOP)
            before = wait_view(stack, lambda v: v["seq"] >= 4, "4 gain updates")
            wait_for(
                lambda: (
                    (snap := snapshot_of(stack.tuner.db, LOOP))
                    and snap[1]["last_t"] >= before["last_sample_t"]
                ),
                "a snapshot of the hidden state after the last update",
            )
            tuner.kill()
            killed_at = plant_log(stack).t[-1]
            during = wait_for(
                lambda: (log := plant_log(stack)).t[-1] > killed_at + 300 and log,
                "300 s of plant time without a tuner",
            )
            last = [m for m in drain(inbox) if m.loop_id == LOOP][-1]
        finally:
            sub.undeclare()
            session.close()
        # the outage starts once the last update the tuner published has landed: it may
        # land after the log's last line read at the kill (the plant flushes its log every
        # 50 scans, up to 50 s of plant time: a CI run saw one land more than 10 s later)
        landed = during.t[np.isclose(during.kp, last.kp, rtol=1e-12) & (during.t > last.t)]
        start = max(killed_at + 10.0, landed[0] if landed.size else -np.inf)
        outage = during.t > start
        assert during.t[-1] - start >= 250.0  # a long outage, the gains held throughout
        assert len(set(during.kp[outage])) == 1 and len(set(during.ki[outage])) == 1
        held = (during.kp[outage][0], during.ki[outage][0])

        stack.start_tuner()
        restored = view(stack)
        assert restored["config"]["kp"] == pytest.approx(REGISTERED[0])  # still registered
        assert restored["seq"] >= before["seq"]
        assert (restored["kp"], restored["ki"]) == pytest.approx(held)
        assert restored["hidden_norm"] > 0, "the agent's state came back from the store"
        after = wait_view(stack, lambda v: v["seq"] >= restored["seq"] + 2, "updates resume")
        assert after["counters"]["rejected"] == 0
        # tuning continued from the held gains (at most +-50% per update, two updates at
        # the limit land on it up to rounding), not from scratch
        limit = 1.5**2 * (1 + 1e-9)
        assert held[0] / limit <= after["kp"] <= held[0] * limit
        assert after["kp"] > 3 * REGISTERED[0]


@pytest.mark.slow
def test_a_plant_waiting_for_its_tuner_gets_each_update_within_the_lag(tmp_path):
    """``pitune plant run --tuner-lag 5`` at a speed no machine keeps up with (10,000x):
    the plant runs at the tuner's pace, and every gain update lands within the lag (and
    a scan or two of the bus) of the sample it answers, as on a machine that keeps up
    (the demo sets it: on a busy machine a 120x plant outran its tuner, and the model's
    first tuning landed 8 simulated minutes late)."""
    lag = 5.0
    with Stack(tmp_path, speed=10_000.0) as stack:
        stack.start_tuner()
        session, sub, inbox = gains_listener(stack)
        try:
            stack.start_plant("--tank", LOOP, "--duration", "900", "--tuner-lag", f"{lag:g}")
            wait_view(stack, lambda v: (v.get("last_sample_t") or 0) >= 899, "the run's end", 120)
            published = [m for m in drain(inbox) if m.loop_id == LOOP]
        finally:
            sub.undeclare()
            session.close()
        log = plant_log(stack)
    assert len(published) >= 2  # one per 165 s of plant time once the loop is excited
    for m in published:
        landed = log.t[np.argmax(np.isclose(log.kp, m.kp, rtol=1e-12) & (log.t > m.t))]
        assert m.t < landed <= m.t + lag + 2.0, (m.t, landed)


@pytest.mark.slow
def test_killed_plant_makes_the_loop_stale_and_silent_until_samples_return(tmp_path):
    with Stack(tmp_path, speed=SPEED) as stack:
        stack.start_tuner()
        session, sub, inbox = gains_listener(stack)
        try:
            plant = stack.start_plant("--tank", LOOP)
            wait_view(stack, lambda v: v["seq"] >= 3, "3 gain updates")
            plant.kill()
            stale = wait_view(stack, lambda v: v["status"] == "stale", "stale", 20)
            drain(inbox)
            time.sleep(3.0)  # an RL step and more of wall time, the loop stale all along
            # The control: a reset of another loop goes out through the same publisher to
            # the same subscription after anything published for tank1 meanwhile.
            with httpx.Client(base_url=stack.api, headers=auth(stack), timeout=5.0) as api:
                probe = {"id": "probe", "kp": 1.0, "ki": 0.1, "sample_period_s": 1.0,
                         "scaling": {"k_hat": 1.0, "tau_hat": 10.0}}  # fmt: skip
                assert api.post("/loops", json=probe).status_code == 201
                assert api.post("/loops/probe/reset").status_code == 200
            published = wait_for(lambda: drain(inbox), "the probe's reset", 10)
            assert [m.loop_id for m in published] == ["probe"], "nothing for a stale loop"
            assert view(stack)["seq"] == stale["seq"]

            stack.start_plant("--tank", LOOP)  # registers again: 409, so it resumes
            fresh = wait_for(lambda: drain(inbox), "gains messages again", 30)
            assert fresh[0].seq > stale["seq"] and fresh[0].t > stale["last_sample_t"]
            assert view(stack)["status"] == "tuning"
            resumed = read_log(stack.log_dir / f"{LOOP}.csv")
            # After the tuner's last sample, not the killed plant's log's last row: its log
            # may hold a sample that never reached the tuner (its clock may resume at that
            # t), or lack the last ones published (buffered when it was killed).
            assert resumed.t[0] > stale["last_sample_t"], "the plant clock continues after it"
            assert resumed.kp[0] == pytest.approx(stale["kp"])
        finally:
            sub.undeclare()
            session.close()


@pytest.mark.slow
def test_reset_over_rest_returns_to_registered_gains_and_starts_over(tmp_path):
    with Stack(tmp_path, speed=SPEED) as stack:
        stack.start_tuner()
        session, sub, inbox = gains_listener(stack)
        try:
            stack.start_plant("--tank", LOOP)
            tuned = wait_view(stack, lambda v: v["kp"] > 3 * REGISTERED[0], "kp tuned up")
            url = f"{stack.api}/loops/{LOOP}/reset"
            assert httpx.post(url, timeout=5.0).status_code == 401  # the token is required
            response = httpx.post(url, headers=auth(stack), timeout=5.0)
            assert response.status_code == 200, response.text
            reset = response.json()
            assert (reset["kp"], reset["ki"]) == pytest.approx(REGISTERED)
            assert reset["hidden_norm"] == 0.0 and reset["seq"] > tuned["seq"]

            collected: list[GainsMessage] = []

            def reset_then_agent():
                collected.extend(drain(inbox))
                since = [m for m in collected if m.seq >= reset["seq"]]
                return since if len(since) >= 2 else None

            first, second = wait_for(reset_then_agent, "reset and the next update", 30)[:2]
            assert first.reason == UpdateReason.reset
            assert (first.kp, first.ki) == pytest.approx(REGISTERED)
            assert second.reason == UpdateReason.agent
            # starting over: the first update moves from the registered gains by <= 50%
            assert REGISTERED[0] / 1.5 <= second.kp <= REGISTERED[0] * 1.5
            log = plant_log(stack)
            applied = log.t[np.isclose(log.kp, REGISTERED[0])]
            assert applied.size and applied[-1] > tuned["last_sample_t"], "the plant applied it"
        finally:
            sub.undeclare()
            session.close()


def test_demo_fails_with_a_clear_message_when_the_tuner_cannot_start(tmp_path):
    argv = [sys.executable, "-m", "service.cli", "demo", "--out", str(tmp_path / "demo"),
            "--agent-weights", str(tmp_path / "missing.pt")]  # fmt: skip
    result = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 1
    assert "pitune demo failed: tuner exited" in result.stderr
    assert "agent weights file not found" in result.stderr
    assert not (tmp_path / "demo").exists()


def test_the_demo_stack_s_plant_listens_on_loopback_only(tmp_path):
    with Stack(tmp_path, speed=SPEED) as stack:
        stack.start_tuner()
        plant = stack.start_plant("--tank", LOOP)
        wait_view(stack, lambda v: v["last_sample_t"] is not None, "samples from the plant")
        addresses = wait_for(lambda: listening(plant.pid), "the plant's Zenoh listener")
        assert set(addresses) <= LOOPBACK, addresses  # not every interface (00000000)


def test_a_terminated_demo_leaves_no_tuner_behind(tmp_path):
    """SIGTERM (a `kill`, a closed terminal's SIGHUP alike) tears the stack down as Ctrl-C
    does: the tuner's API is gone when the demo has exited."""
    argv = [sys.executable, "-m", "service.cli", "demo", "--out", str(tmp_path / "demo"),
            "--speed", "150"]  # fmt: skip
    demo = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)  # fmt: skip
    try:
        console = ""
        for line in demo.stdout:
            if line.startswith("operator console: "):
                console = line.split()[2]
            if line.startswith("plant simulator started"):
                break
        assert console, demo.stderr.read()
        demo.send_signal(signal.SIGTERM)
        assert demo.wait(timeout=30) == 128 + signal.SIGTERM
        with pytest.raises(httpx.TransportError):
            httpx.get(console, timeout=2)
    finally:  # an orphan of a failed run is in the demo's process group
        with contextlib.suppress(ProcessLookupError):
            os.killpg(demo.pid, signal.SIGKILL)
        demo.wait()


def test_gains_the_plant_clamps_are_adopted_and_the_tuners_view_follows_them(tmp_path):
    """``pitune plant run --gain-range 2``: the simulated PI block takes gains within a
    factor 2 of the registered ones and clamps the tuner's beyond. Its samples say which
    update they follow (``applied_seq``), so the tuner adopts the clamped gains (an
    ``adopted`` row) and its view shows the gains the plant runs. Without ``applied_seq``
    (0: none applied) the tuner took every clamped report for an update in flight, and
    its view kept gains the plant never ran."""
    bound = (2 * REGISTERED[0], 2 * REGISTERED[1])
    with Stack(tmp_path, speed=SPEED) as stack:
        stack.start_tuner()
        plant = stack.start_plant("--tank", LOOP, "--gain-range", "2")

        def adopted():
            response = httpx.get(f"{stack.api}/loops/{LOOP}/history?limit=1000", timeout=5.0)
            rows = response.json()["items"] if response.is_success else []
            return [r for r in rows if r["reason"] == "adopted"]

        row = wait_for(adopted, "gains adopted from the plant", 60)[-1]
        clamped = (row["kp_new"], row["ki_new"])
        # the update the plant clamped: above the bound in one gain at least
        assert row["kp_old"] > bound[0] * (1 + 1e-9) or row["ki_old"] > bound[1] * (1 + 1e-9)
        assert clamped == pytest.approx(np.minimum((row["kp_old"], row["ki_old"]), bound))
        wait_view(stack, lambda v: (v["kp"], v["ki"]) == pytest.approx(clamped), "the view")
        assert plant.stop() == 0, plant.tail()
    log = plant_log(stack)
    assert log.kp.max() <= bound[0] * (1 + 1e-9) and log.ki.max() <= bound[1] * (1 + 1e-9)
    assert np.any(np.isclose(log.kp, clamped[0], rtol=1e-9))
