"""Set-up: the Quick start's install as CI runs it, and an install without a C compiler
(the kernel extension is optional): the fast path falls back to the agent's torch
``act``, says so once in the log, and tunes the same."""

import subprocess
import sys

from service.procs import ROOT

SCRIPT = r"""
import logging, sys
sys.modules["service.agent._gru"] = None  # as if the optional extension was not built
logging.basicConfig(level=logging.WARNING, format="%(name)s %(message)s")
import numpy as np
from service.agent import fast, load_agent
from service.engine import LoopConfig, TuningEngine

assert not fast.KERNEL
agent = load_agent()
policy = fast.FastPolicy(agent, workers=2)
rng = np.random.default_rng(0)
obs = np.column_stack([rng.uniform(0.05, 2, (300, 2)), rng.normal(size=(300, 2))])
state = (rng.normal(size=(300, 2, 100)) * 0.3).astype(np.float32)
want, want_state = agent.act(obs, state, 0.99)
got = policy.step_inplace(obs, state, 0.99)
assert np.array_equal(got, want) and np.array_equal(state, want_state)
fast.FastPolicy(agent)  # a second policy: no second warning
eng = TuningEngine(agent)
eng.register(LoopConfig(id="L", kp=0.02, ki=0.0003, sample_period_s=1.0,
                        scaling={"k_hat": 1.2, "tau_hat": 30.0, "pv_scale": 10.0},
                        guard={"excitation_periods": 0}))
ups = eng.ingest([{"loop_id": "L", "t": float(i), "e": 1.0} for i in range(400)])
print("updates", len(ups), eng.table.inference_precision)
"""


def test_without_the_c_kernel_inference_falls_back_to_torch_with_one_log_line():
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "updates 2 float32" in proc.stdout
    warnings = [line for line in proc.stderr.splitlines() if "C kernel" in line]
    assert len(warnings) == 1 and warnings[0].startswith("pitune.agent ")
    assert "inference runs on torch" in warnings[0] and "gcc" in warnings[0]


def test_the_kernels_are_optional_extensions_and_the_license_an_spdx_expression():
    """No C compiler: the install goes on without the extensions (setuptools' optional),
    and the fallbacks run (the agent's above; training's numpy sample loop, compared with
    the C one in tests/test_learn_v3.py). The license is an SPDX string (PEP 639):
    setuptools drops the TOML-table form in 2027."""
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    exts = project["tool"]["setuptools"]["ext-modules"]
    assert {e["name"] for e in exts} == {"service.agent._gru", "service.learn._period"}
    assert all(e["optional"] is True for e in exts)
    assert project["project"]["license"] == "Apache-2.0"


def test_ci_installs_torch_exactly_as_the_readme_quick_start():
    """CI runs the README's install literally: the same torch command, from the CPU index."""
    readme = (ROOT / "README.md").read_text()
    quick = readme.split("## Quick start", 1)[1].split("```bash\n", 1)[1].split("\n", 1)[0]
    torch_cmd = next(p.strip() for p in quick.split("&&") if "torch==" in p)
    assert "--index-url https://download.pytorch.org/whl/cpu" in torch_cmd
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert torch_cmd.replace("pip install", "pip install -q") in ci
