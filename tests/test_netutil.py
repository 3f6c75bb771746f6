"""service.wire.session: the one Zenoh config builder of every pitune process, and free_port."""

import json
import socket

from service.wire.session import free_port, session_config


def get(config, path):
    return json.loads(config.get_json(path))


def test_without_a_file_multicast_scouting_is_off_and_options_apply():
    c = session_config(mode="client", connect=["tcp/127.0.0.1:7447"])
    assert get(c, "mode") == "client"
    assert get(c, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    assert get(c, "scouting/multicast/enabled") is False
    assert get(session_config(multicast_scouting=True), "scouting/multicast/enabled") is True


def test_a_file_is_overridden_only_by_the_options_given(tmp_path):
    path = tmp_path / "gateway.json5"
    path.write_text(
        '{ mode: "client", connect: { endpoints: ["tcp/router:7447"] },\n'
        "  scouting: { multicast: { enabled: true } },\n"
        '  transport: { auth: { usrpwd: { user: "gateway", password: "pw" } } } }\n'
    )
    c = session_config(config_file=path)
    assert (get(c, "mode"), get(c, "connect/endpoints")) == ("client", ["tcp/router:7447"])
    assert get(c, "scouting/multicast/enabled") is True
    c = session_config(config_file=str(path), connect=["tcp/10.0.0.5:7447"], listen=[])
    assert get(c, "connect/endpoints") == ["tcp/10.0.0.5:7447"]
    assert get(c, "listen/endpoints") == []
    assert get(c, "mode") == "client" and get(c, "scouting/multicast/enabled") is True
    assert get(c, "transport/auth/usrpwd/user") == "gateway"


def test_free_port_is_bindable_on_loopback():
    with socket.socket() as s:
        s.bind(("127.0.0.1", free_port()))
