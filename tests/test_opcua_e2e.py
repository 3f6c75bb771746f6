"""End to end through OPC UA: the simulated DCS (``pitune plant opcua``), the gateway
(``pitune gateway opcua``) and the tuner (``pitune tuner``), each its own process, tune
the two-tank level loop as well as the direct simulator (``pitune plant run``) does:
the demo's tracking MSE within 20 %."""

from __future__ import annotations

import tomllib

import pytest
import tomli_w

from plant_sim.config import LoopSpec, Simulation
from plant_sim.process import plant_argv
from plant_sim.trajectory import read_log
from service.procs import Proc, Stack, TunerProcess, clean_env, pitune
from service.wire.session import free_port

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]
LOOP = LoopSpec("two_tank", "tank1")
SPEED = 60.0
SIM = Simulation(duration=3600.0, speed=SPEED)
MSE_CHANGES = 2


def direct_run(workdir) -> float:
    """The demo: ``pitune plant run`` straight on the bus; its tracking MSE."""
    with Stack(workdir, speed=SPEED) as st:
        st.start_tuner()
        plant = st.start_plant(*plant_argv((LOOP,), SIM))
        assert plant.wait(SIM.duration / SPEED + 120) == 0, plant.tail()
    return read_log(st.log_dir / "tank1.csv").tracking_mse(MSE_CHANGES)


def opcua_run(workdir) -> tuple[float, dict, str]:
    """The same loop as a PID block of the simulated DCS, through the OPC UA gateway."""
    tuner = TunerProcess(workdir / "pitune.db", "--max-sample-rate", f"{4 * SPEED:g}",
                         "--log-level", "warning", log=workdir / "tuner.log",
                         token="e2e-token")  # fmt: skip
    procs: list[Proc] = []
    try:
        tuner.start()
        raw_map = workdir / "dcs-map.toml"
        dcs = Proc("dcs", pitune("plant", "opcua", *plant_argv((LOOP,), SIM), "--port",
                                 str(free_port()), "--allow-insecure", "--write-map",
                                 str(raw_map), "--log-dir", str(workdir / "log"),
                                 "--progress", "0", "--wait-for-gateway"),
                   log=workdir / "dcs.log")  # fmt: skip
        procs.append(dcs)
        dcs.wait_ready(raw_map.exists, timeout=60)
        site = tomllib.loads(raw_map.read_text())
        site["bus"] = {"connect": [tuner.zenoh], "gateway_id": "opcua-e2e"}
        site["tuner"] = {"register_url": tuner.api}
        for loop in site["loops"]:
            loop["min_write_interval_s"] = 0.5  # wall seconds; an RL step is 2.75 s at 60x
        site_file = workdir / "site.toml"
        site_file.write_text(tomli_w.dumps(site))
        gateway = Proc("gateway", pitune("gateway", "opcua", "--map", str(site_file),
                                         "--log-level", "info"),
                       log=workdir / "gateway.log",
                       env=clean_env(PITUNE_API_TOKEN="e2e-token"))  # fmt: skip
        procs.append(gateway)
        assert dcs.wait(SIM.duration / SPEED + 120) == 0, dcs.tail()
        with tuner.http() as http:
            view = http.get("/loops/tank1").json()
        assert gateway.stop() == 0, gateway.tail()
        return (
            read_log(workdir / "log" / "tank1.csv").tracking_mse(MSE_CHANGES),
            view,
            gateway.tail(),
        )
    finally:
        for proc in reversed(procs):
            proc.stop()
        tuner.stop()


def test_two_tank_tuned_through_opc_ua_as_well_as_directly(tmp_path):
    mse_opcua, view, gateway_log = opcua_run(tmp_path / "opcua")
    mse_direct = direct_run(tmp_path / "direct")
    print(f"tracking MSE through OPC UA {mse_opcua:.4g} cm^2, direct {mse_direct:.4g} cm^2; "
          f"{view['seq']} updates; gateway: {gateway_log.splitlines()[-1]}")  # fmt: skip
    assert view["config"]["gateway"] == "opcua-e2e"  # registered by the gateway, batched gains
    assert view["seq"] >= 10
    assert mse_opcua <= 1.2 * mse_direct
