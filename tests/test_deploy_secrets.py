"""deploy/secrets.sh: the compose deployment's Zenoh passwords, fresh and random, with a
user of its own for each gateway named (the ACL's per-gateway users), checked live in the
router the deployment runs (deploy/zenoh_router.py with deploy/zenoh/router.json5)."""

from __future__ import annotations

import queue
import re
import shutil
import stat
import subprocess
from pathlib import Path

import pytest
import zenoh

from service.wire.protocol import LOOP_ID_PATTERN, Keys
from service.wire.session import session_config
from tests.test_deploy_acl_live import DEPLOY, first_through, python_router

SCRIPT = DEPLOY / "secrets.sh"
KEYS = Keys()


def secrets(target: Path, *gateways: str, script: Path = SCRIPT) -> subprocess.CompletedProcess:
    return subprocess.run(
        ["bash", str(script), str(target), *gateways], capture_output=True, text=True
    )


def users_of(target: Path) -> dict[str, str]:
    return dict(line.split(":") for line in (target / "credentials.txt").read_text().split())


def test_secrets_sh_makes_fresh_passwords_in_a_private_directory(tmp_path):
    target = tmp_path / "secrets"
    made = secrets(target)
    assert made.returncode == 0, made.stderr
    assert stat.S_IMODE(target.stat().st_mode) == 0o700
    users = users_of(target)
    assert set(users) == {"tuner", "gateway"} and len(set(users.values())) == 2
    for user, password in users.items():
        config = (target / f"{user}.json5").read_text()
        assert password in config and "change-me" not in config
        assert len(password) == 32
    again = secrets(target)
    assert again.returncode == 1 and "not empty" in again.stderr
    assert users_of(target) == users


def client(config: Path, endpoint: str) -> zenoh.Session:
    return zenoh.open(session_config(config_file=config, connect=[endpoint]))


def test_secrets_sh_makes_the_per_gateway_users_the_acl_names(tmp_path):
    """``secrets.sh DIR gw-1``: the ACL's example per-gateway user gets a password and a
    client config; through the router, on that directory's credentials, it logs in and
    its gateway's samples reach the tuner user."""
    target = tmp_path / "secrets"
    made = secrets(target, "gw-1")
    assert made.returncode == 0, made.stderr
    users = users_of(target)
    assert set(users) == {"tuner", "gateway", "gateway-gw-1"}
    assert len(set(users.values())) == 3 and {len(pw) for pw in users.values()} == {32}
    config = (target / "gateway-gw-1.json5").read_text()
    assert f'user: "gateway-gw-1", password: "{users["gateway-gw-1"]}"' in config
    assert stat.S_IMODE((target / "gateway-gw-1.json5").stat().st_mode) == 0o644
    key = KEYS.gateway_samples("gw-1")
    got: queue.SimpleQueue = queue.SimpleQueue()
    with (
        python_router(tmp_path, credentials=target / "credentials.txt") as endpoint,
        client(target / "tuner.json5", endpoint) as tuner,
        client(target / "gateway-gw-1.json5", endpoint) as gateway,
        tuner.declare_subscriber(key, lambda s: got.put(s.payload.to_bytes())),
    ):
        first_through(lambda: gateway.put(key, b"{}"), got)


def test_secrets_sh_refuses_a_gateway_the_acl_does_not_name_and_makes_nothing(tmp_path):
    """A user the ACL does not grant would log in and be allowed nothing (default deny):
    refused, as are an id that is not one and an id given twice; no directory is made."""
    target = tmp_path / "secrets"
    for gateways, message in [
        (("gw-1", "unit-7"), "the router's ACL"),
        (("gw-1", "a/b"), "'a/b' is not a gateway id"),
        (("-x",), "'-x' is not a gateway id"),
        (("gw-1", "gw-1"), "gateway 'gw-1' is given twice"),
    ]:
        refused = secrets(target, *gateways)
        assert refused.returncode == 1, gateways
        assert message in refused.stderr and refused.stderr.count("\n") == 1, refused.stderr
        assert not target.exists(), gateways
    assert "no user gateway-unit-7" in secrets(target, "unit-7").stderr


def _deploy_copy(tmp_path: Path) -> Path:
    """A copy of deploy/'s script and Zenoh configs, to edit a router config."""
    deploy = tmp_path / "deploy"
    (deploy / "zenoh").mkdir(parents=True)
    shutil.copy(SCRIPT, deploy)
    for example in (DEPLOY / "zenoh").glob("*.json5"):
        shutil.copy(example, deploy / "zenoh")
    return deploy


def test_secrets_sh_refuses_a_gateway_the_tls_router_does_not_name(tmp_path):
    """A TLS site runs router-tls.json5: a user only router.json5 grants would log in
    there and be allowed nothing, so the script checks both configs (a copy of deploy/
    whose TLS config lacks gw-1's user)."""
    deploy = _deploy_copy(tmp_path)
    tls = deploy / "zenoh" / "router-tls.json5"
    tls.write_text(tls.read_text().replace('"gateway-gw-1"', '"gateway-gw-9"'))
    target = tmp_path / "secrets"
    refused = secrets(target, "gw-1", script=deploy / "secrets.sh")
    assert refused.returncode == 1 and not target.exists()
    assert f"ACL ({tls}) has no user gateway-gw-1" in refused.stderr, refused.stderr


GW1 = '      { id: "gateway-gw-1", usernames: ["gateway-gw-1"] },'
GW2 = '{ id: "gateway-gw-2", usernames: ["gateway-gw-2"] },'
ACLS = ("router.json5", "router-tls.json5")


def _after_gw1(acl: Path, line: str) -> None:
    acl.write_text(acl.read_text().replace(GW1, f"{GW1}\n{line}"))


@pytest.mark.parametrize("config", ACLS)
@pytest.mark.parametrize(
    "named",
    [
        f"      // {GW2}  (to do)",  # a line commented out
        f"{GW1}  // {GW2}",  # a note after another subject
    ],
    ids=["commented-out", "note-after-another"],
)
def test_secrets_sh_refuses_a_gateway_named_only_in_a_comment(tmp_path, config, named):
    """The router grants nothing to a subject in a ``//`` comment: a config naming gw-2
    only there (the other config granting it) is refused, nothing written."""
    deploy = _deploy_copy(tmp_path)
    for acl in ACLS:
        _after_gw1(deploy / "zenoh" / acl, named if acl == config else f"      {GW2}")
    target = tmp_path / "secrets"
    refused = secrets(target, "gw-2", script=deploy / "secrets.sh")
    acl = deploy / "zenoh" / config
    assert refused.returncode == 1 and not target.exists(), refused.stderr
    assert f"ACL ({acl}) has no user gateway-gw-2" in refused.stderr, refused.stderr


def test_secrets_sh_takes_a_subject_with_a_comment_after_it(tmp_path):
    """A note after a granted subject's line does not hide it."""
    deploy = _deploy_copy(tmp_path)
    for acl in ACLS:
        _after_gw1(deploy / "zenoh" / acl, f"      {GW2}  // unit 2")
    target = tmp_path / "secrets"
    made = secrets(target, "gw-2", script=deploy / "secrets.sh")
    assert made.returncode == 0, made.stderr
    assert set(users_of(target)) == {"tuner", "gateway", "gateway-gw-2"}


def test_secrets_sh_takes_the_gateway_ids_the_tuner_takes():
    """The script's id rule is the protocol's (one rule, two languages)."""
    pattern = re.search(r"^ID_PATTERN='(.*)'$", SCRIPT.read_text(), re.M)
    assert pattern is not None
    assert pattern.group(1) == LOOP_ID_PATTERN.replace("\\-", "-")
