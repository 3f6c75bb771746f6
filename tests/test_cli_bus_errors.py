"""A Zenoh session that cannot open is one line, not a traceback, in every program that
joins the bus: the plant simulator and the OPC UA gateway say it as the tuner does
(``service.wire.session.join_failure``): status 2 when the endpoint or config is
malformed, 1 when an address cannot be used. Real subprocesses, real Zenoh."""

from __future__ import annotations

import subprocess
import sys

import pytest

from service.procs import ROOT, clean_env

pytestmark = pytest.mark.timeout(120)
GATEWAY_MAP = """\
[server]
url = "opc.tcp://127.0.0.1:1/pitune/dcs"
security = "None"
allow_insecure = true

[[loops]]
id = "tank1"
sp = "ns=2;s=tank1.SP"
pv = "ns=2;s=tank1.PV"
op = "ns=2;s=tank1.OUT"
p = "ns=2;s=tank1.GAIN"
i = "ns=2;s=tank1.RESET"

[loops.registration]
sample_period_s = 1.0

[loops.registration.scaling]
k_hat = 1.2
tau_hat = 30.0

[loops.form]
p = "gain"
i = "reset_min"
pv_span = 120.0
op_span = 80.0

[loops.limits]
p = [0.0003, 3.0]
i = [0.01, 100.0]

[bus]
connect = ["bogus"]
"""


def pitune(*args: str) -> subprocess.CompletedProcess:
    argv = [sys.executable, "-m", "service.cli", *args]
    return subprocess.run(argv, cwd=ROOT, env=clean_env(), capture_output=True, text=True,
                          timeout=90)  # fmt: skip


def one_line(proc: subprocess.CompletedProcess, code: int, *words: str) -> None:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == code, proc.stderr
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for word in words:
        assert word in lines[0], lines[0]
    assert ".rs:" not in lines[0]  # no Rust source locations


@pytest.fixture
def busy_port():
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


def test_the_plant_simulator_says_why_it_cannot_join_the_bus(tmp_path, busy_port):
    run = ("plant", "run", "--duration", "5")
    one_line(pitune(*run, "--connect", "bogus"), 2, "pitune plant: invalid Zenoh endpoint",
             "--connect bogus", "tcp/127.0.0.1:7447")  # fmt: skip
    broken = tmp_path / "zenoh.json5"
    broken.write_text('{ mode: "peer", listen: { endpoints: [\n')
    one_line(pitune(*run, "--zenoh-config", str(broken)), 2, "invalid Zenoh endpoint or config",
             f"--zenoh-config {broken}")  # fmt: skip
    one_line(pitune(*run, "--listen", f"tcp/127.0.0.1:{busy_port}"), 1,
             "pitune plant: cannot join the Zenoh bus", "Address already in use")  # fmt: skip


def test_the_opcua_gateway_says_its_maps_bus_is_wrong(tmp_path):
    site = tmp_path / "site.toml"
    site.write_text(GATEWAY_MAP)
    proc = pitune("gateway", "opcua", "--map", str(site))
    one_line(proc, 2, "pitune gateway opcua: invalid Zenoh endpoint", "[bus]", "bogus")
