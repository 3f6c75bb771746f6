"""A tiny run of the load benchmark (``pitune bench``), so that it cannot rot. Rates and
latencies depend on the machine's load: checked for consistency, not against a range."""

from __future__ import annotations

import argparse
import json

import pytest

from service import bench as load
from service.bench.command import bench_config
from service.bench.config import BenchConfig

pytestmark = pytest.mark.slow


def test_tiny_benchmark_run_measures_everything(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    load.add_arguments(parser)
    args = parser.parse_args(
        [
            "--loops", "30", "--rate", "10", "--duration", "3", "--warmup", "1",
            "--tau", "0.3", "0.5",  # RL steps every 1.65..2.75 s of plant time
            "--memory-probe", "10", "--agent-weights", "untrained",
            "--out", str(tmp_path),
        ]
    )  # fmt: skip
    assert bench_config(args) == BenchConfig(
        loops=30, rate=10, duration=3, warmup=1, tau=(0.3, 0.5), memory_probe=10,
        agent_weights="untrained", out=tmp_path,
    )  # fmt: skip
    assert load.run(args) == 0
    (path,) = tmp_path.glob("*-30x10hz.json")
    result = json.loads(path.read_text())
    samples, updates = result["samples"], result["updates"]
    assert samples["lost"] == 0 and samples["rejected"] == 0
    assert samples["published"] == 30 * 10 * 4
    # the window's samples are a part of the run's, whatever the generator's lag
    assert 0 < samples["published_per_s"] * 3 <= samples["published"]
    assert updates["gains_in_window"] > 0 and updates["unmatched"] == 0
    lat = updates["latency_ms"]
    assert 0 < lat["p50"] <= lat["p99"] <= lat["max"] < 5000
    assert result["daemon"]["rss_max_mb"] > 0 and result["daemon"]["cpu_percent"] > 0
    assert "rss_per_loop_kb" in result["daemon"]
    assert result["inference"]["loops"] == 30
    assert result["bar"]["samples_lost"]["met"] is True
    assert result["daemon_exit"] is not None
    assert result["config"]["tau"] == [0.3, 0.5] and result["config"]["out"] == str(tmp_path)
    assert result["machine_cpu"]["busy_percent"] > 0 and result["machine"]["cpus"] >= 1
    assert updates["gains_received"] >= updates["gains_in_window"]  # from GainsBatch messages
    out = capsys.readouterr().out
    assert "update latency p50 / p99 / max" in out and "bar:" in out
    assert "batched gains" in out


def test_aligned_per_loop_variant(tmp_path):
    parser = argparse.ArgumentParser()
    load.add_arguments(parser)
    args = parser.parse_args(
        [
            "--loops", "8", "--rate", "10", "--duration", "2", "--warmup", "0.5",
            "--tau", "0.3", "0.3", "--aligned", "--per-loop", "--memory-probe", "0",
            "--agent-weights", "untrained", "--no-inference-bench", "--out", str(tmp_path),
        ]
    )  # fmt: skip
    assert load.run(args) == 0
    (path,) = tmp_path.glob("*-8x10hz-aligned-perloop.json")
    result = json.loads(path.read_text())
    assert result["samples"]["lost"] == 0 and result["samples"]["rejected"] == 0
    # all 8 loops fall due in the same sample: every step is one batch of 8
    assert result["updates"]["gains_in_window"] % 8 == 0
    assert result["inference"] is None


def test_monitor_ab_pairs_runs_with_the_monitoring_on_and_off(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    load.add_arguments(parser)
    args = parser.parse_args(
        [
            "--loops", "20", "--rate", "10", "--duration", "2", "--warmup", "0.5",
            "--tau", "0.3", "0.5", "--memory-probe", "0", "--agent-weights", "untrained",
            "--monitor-ab", "1", "--out", str(tmp_path),
        ]
    )  # fmt: skip
    assert load.run(args) == 0
    (path,) = tmp_path.glob("*-20-monitor-ab.json")
    result = json.loads(path.read_text())
    runs = result["runs"]
    assert [r["monitoring"] for r in runs] == [True, False]
    assert all(r["cpu_us_per_sample"] > 0 and r["lost"] == 0 for r in runs)
    added = 100.0 * (runs[0]["cpu_us_per_sample"] / runs[1]["cpu_us_per_sample"] - 1.0)
    assert result["added_cpu_pct"]["median"] == pytest.approx(added)
    assert result["bar"]["met"] == (added < 20.0)
    assert "monitoring adds" in capsys.readouterr().out


def test_guard_option_reaches_every_registration_and_bad_settings_are_refused(capsys):
    """``--guard JSON`` adds guard settings to each loop's registration (what an opt-in
    measure costs at the benchmark's load), checked before anything starts."""
    from service.bench.fleet import Fleet

    parser = argparse.ArgumentParser()
    load.add_arguments(parser)
    args = parser.parse_args(["--loops", "3", "--guard", '{"identify": true}'])
    config = bench_config(args)
    assert config.guard == {"identify": True}
    guards = [r["guard"] for r in Fleet(config).registrations]
    assert guards == [{"excitation_periods": 0.0, "identify": True}] * 3
    assert [r["guard"] for r in Fleet(BenchConfig(loops=2)).registrations] == [
        {"excitation_periods": 0.0}
    ] * 2
    with pytest.raises(SystemExit):
        parser.parse_args(["--guard", '{"identify": "maybe"}'])
    assert "not a loop's guard settings" in capsys.readouterr().err


def test_no_hint_registers_every_loop_without_a_scaling():
    """``--no-hint``: the loops registered without a scaling (identified before they are
    tuned); by default each has its hint, the same as before the option."""
    from service.bench.fleet import Fleet

    parser = argparse.ArgumentParser()
    load.add_arguments(parser)
    config = bench_config(parser.parse_args(["--loops", "3", "--no-hint"]))
    assert [r["scaling"] for r in Fleet(config).registrations] == [None] * 3
    hinted = Fleet(BenchConfig(loops=3)).registrations
    assert all(r["scaling"]["tau_hat"] > 0 and r["scaling"]["pv_scale"] == 1.0 for r in hinted)
