"""Settings precedence (flags > env > file > defaults) and the Zenoh config they produce."""

import argparse
import json

import pytest
from pydantic import ValidationError

from service.daemon import main as daemon
from service.daemon.bus import zenoh_config
from service.daemon.settings import load_settings

pytestmark = pytest.mark.timeout(30)


def test_flags_beat_environment_beat_file_beat_defaults(tmp_path, monkeypatch):
    config = tmp_path / "pitune.toml"
    config.write_text('api_port = 9001\nkey_prefix = "site/pitune"\ndb_path = "/var/x.db"\n')
    monkeypatch.setenv("PITUNE_API_PORT", "9002")
    monkeypatch.setenv("PITUNE_ZENOH_CONNECT", '["tcp/10.0.0.5:7447"]')
    parser = argparse.ArgumentParser()
    daemon.add_arguments(parser)
    listen = ["--listen", "tcp/127.0.0.1:1", "--listen", "tcp/127.0.0.1:2"]
    args = parser.parse_args(["--config", str(config), "--db", "/tmp/flag.db", *listen])
    overrides = {f: getattr(args, f) for f in daemon.FLAGS if hasattr(args, f)}
    s = load_settings(args.config, **overrides)
    assert str(s.db_path) == "/tmp/flag.db"  # flag over file
    assert s.api_port == 9002  # environment over file
    assert s.key_prefix == "site/pitune"  # file over default
    assert s.zenoh_connect == ["tcp/10.0.0.5:7447"]
    assert s.zenoh_listen == ["tcp/127.0.0.1:1", "tcp/127.0.0.1:2"]
    assert s.api_host == "127.0.0.1" and s.api_token is None  # defaults

    monkeypatch.setenv("PITUNE_CONFIG", str(config))
    assert load_settings().key_prefix == "site/pitune"
    with pytest.raises(FileNotFoundError):
        load_settings(tmp_path / "missing.toml")
    with pytest.raises(ValidationError):
        load_settings(key_prefix="a/*")
    with pytest.raises(ValidationError):
        load_settings(instance_id="has/slash")


def test_default_zenoh_config_is_a_loopback_peer_without_scouting():
    c = zenoh_config(load_settings())
    assert json.loads(c.get_json("mode")) == "peer"
    assert json.loads(c.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(c.get_json("connect/endpoints")) == []
    assert json.loads(c.get_json("scouting/multicast/enabled")) is False


def test_a_zenoh_config_file_is_overridden_only_by_explicit_settings(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text(
        '{ mode: "client", connect: { endpoints: ["tcp/router:7447"] },\n'
        '  transport: { auth: { usrpwd: { user: "tuner", password: "pw" } } } }\n'
    )
    c = zenoh_config(load_settings(zenoh_config=path))
    assert json.loads(c.get_json("mode")) == "client"
    assert json.loads(c.get_json("connect/endpoints")) == ["tcp/router:7447"]
    assert json.loads(c.get_json("transport/auth/usrpwd/user")) == "tuner"
    c = zenoh_config(load_settings(zenoh_config=path, zenoh_connect=["tcp/10.1.1.1:7447"]))
    assert json.loads(c.get_json("connect/endpoints")) == ["tcp/10.1.1.1:7447"]
    assert json.loads(c.get_json("mode")) == "client"


@pytest.mark.parametrize("value", ["", "  "])
def test_an_empty_api_token_is_no_token(monkeypatch, value):
    monkeypatch.setenv("PITUNE_API_TOKEN", value)
    assert load_settings().api_token is None
    monkeypatch.setenv("PITUNE_API_TOKEN", "s3cret")
    assert load_settings().api_token.get_secret_value() == "s3cret"


def test_choices_in_any_case_and_endpoints_as_json_or_comma_separated(monkeypatch):
    monkeypatch.setenv("PITUNE_LOG_LEVEL", "INFO")
    monkeypatch.setenv("PITUNE_LOG_FORMAT", "Json")
    monkeypatch.setenv("PITUNE_ZENOH_MODE", "CLIENT")
    monkeypatch.setenv("PITUNE_ZENOH_CONNECT", "tcp/10.0.0.5:7447, tcp/10.0.0.6:7447")
    monkeypatch.setenv("PITUNE_ZENOH_LISTEN", "tcp/0.0.0.0:7447")
    s = load_settings()
    assert (s.log_level, s.log_format, s.zenoh_mode) == ("info", "json", "client")
    assert s.zenoh_connect == ["tcp/10.0.0.5:7447", "tcp/10.0.0.6:7447"]
    assert s.zenoh_listen == ["tcp/0.0.0.0:7447"]
    monkeypatch.setenv("PITUNE_ZENOH_CONNECT", '["tcp/10.0.0.5:7447"]')
    monkeypatch.setenv("PITUNE_LOG_LEVEL", "warn")
    s = load_settings()
    assert s.zenoh_connect == ["tcp/10.0.0.5:7447"] and s.log_level == "warning"
    monkeypatch.setenv("PITUNE_ZENOH_CONNECT", "")
    assert load_settings().zenoh_connect == []
    monkeypatch.setenv("PITUNE_ZENOH_CONNECT", '["tcp/10.0.0.5:7447"')
    with pytest.raises(ValidationError, match="JSON"):
        load_settings()


def test_pitune_db_is_an_alias_and_unknown_variables_are_named(tmp_path, monkeypatch):
    from service.daemon.settings import unknown_variables

    config = tmp_path / "pitune.toml"
    config.write_text('db_path = "/from/file.db"\n')
    monkeypatch.setenv("PITUNE_DB", "/from/alias.db")
    assert str(load_settings(config).db_path) == "/from/alias.db"  # over the file
    assert str(load_settings(config, db_path="/flag.db").db_path) == "/flag.db"
    monkeypatch.setenv("PITUNE_DB_PATH", "/from/own.db")
    assert str(load_settings(config).db_path) == "/from/own.db"  # its own name wins
    environ = {
        "PITUNE_DB": "x", "PITUNE_API_TOKEN": "t", "PITUNE_CONFIG": "c", "PITUNE_TLS_DIR": "d",
        "PITUNE_LOGLEVEL": "INFO", "PITUNE_SNAPSHOT_INTERVAL": "5", "PITUNE_XYZZY": "1",
        "HOME": "/root",
    }  # fmt: skip
    assert unknown_variables(environ) == [
        "environment variable PITUNE_LOGLEVEL is not a tuner setting, ignored; "
        "did you mean PITUNE_LOG_LEVEL?",
        "environment variable PITUNE_SNAPSHOT_INTERVAL is not a tuner setting, ignored; "
        "did you mean PITUNE_SNAPSHOT_INTERVAL_S?",
        "environment variable PITUNE_XYZZY is not a tuner setting, ignored",
    ]


def test_flags_take_choices_in_any_case():
    parser = argparse.ArgumentParser()
    daemon.add_arguments(parser)
    args = parser.parse_args(["--log-level", "DEBUG", "--zenoh-mode", "Client"])
    assert (args.log_level, args.zenoh_mode) == ("debug", "client")


SECRET = "S3cret-gateway-token-0123456789"


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"api_gateway_tokens": {"gw 1": SECRET}}, "'gw 1' is not a gateway id"),
        ({"api_gateway_tokens": {"gw/1": SECRET}}, "'gw/1' is not a gateway id"),
        ({"api_gateway_tokens": {"gw-1": ""}}, "gateway 'gw-1' has an empty token"),
        ({"api_gateway_tokens": {"gw-1": "  "}}, "gateway 'gw-1' has an empty token"),
        (
            {"api_gateway_tokens": {"gw-1": SECRET, "gw-2": SECRET}},
            "gateways 'gw-1' and 'gw-2' have the same token",
        ),
        (
            {"api_token": SECRET, "api_gateway_tokens": {"gw-1": SECRET}},
            "the token of gateway 'gw-1' is the admin token",
        ),
    ],
)
def test_gateway_tokens_that_cannot_work_as_meant_are_refused(monkeypatch, settings, message):
    """Accepted before: a key no registration can name (its token useless), an empty
    token, one token for two gateways (the gate took it for one of them), and the admin
    token as a gateway's (checked first: that gateway was an admin). Refused, the message
    naming the gateway and never the token, from the environment too."""
    with pytest.raises(ValidationError) as refused:
        load_settings(**settings)
    [error] = refused.value.errors()
    assert error["loc"] == ("api_gateway_tokens",) and message in error["msg"]
    assert SECRET not in error["msg"]
    tokens = {"gw-1": SECRET, "gw_2.b": SECRET + "-2"}  # ids, tokens of their own
    assert load_settings(api_token="admin-0123456789ab", api_gateway_tokens=tokens)
    if "api_token" in settings:
        monkeypatch.setenv("PITUNE_API_TOKEN", settings["api_token"])
    monkeypatch.setenv("PITUNE_API_GATEWAY_TOKENS", json.dumps(settings["api_gateway_tokens"]))
    with pytest.raises(ValidationError, match=message):
        load_settings()
