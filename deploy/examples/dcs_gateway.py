"""A minimal DCS gateway for pitune: publish a loop's samples, apply its ``auto`` gains.

Replace ``read_loop`` and ``write_gains`` with your DCS's calls (OPC UA, Modbus, ...).
Run it beside a tuner on this host, or through the compose deployment's router:

    python deploy/examples/dcs_gateway.py --connect tcp/127.0.0.1:7447
    python deploy/examples/dcs_gateway.py --config deploy/zenoh/gateway.json5
"""

import argparse
import json
import queue
import time

import zenoh

from service.protocol import GainsMessage, Keys, Mode, Sample, encode

LOOP_ID = "LIC-101"
gains = {"kp": 0.5, "ki": 0.01}  # the DCS PID block's gains (stand-in)


def read_loop() -> tuple[float, float]:
    """Setpoint and measurement from the DCS (stand-in: a loop at rest)."""
    return 55.0, 54.8


def write_gains(kp: float, ki: float) -> None:
    """Write new gains to the DCS PID block (bumpless in the DCS)."""
    gains.update(kp=kp, ki=ki)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--connect", default=None, help="Zenoh endpoint of the tuner or router")
    parser.add_argument("--config", default=None, help="Zenoh JSON5 config (auth, router)")
    parser.add_argument("--seconds", type=float, default=float("inf"), help="stop after this")
    args = parser.parse_args()
    config = zenoh.Config.from_file(args.config) if args.config else zenoh.Config()
    if args.connect:
        config.insert_json5("connect/endpoints", json.dumps([args.connect]))
    keys, inbox = Keys(), queue.SimpleQueue()
    with zenoh.open(config) as session:
        # Never block in a Zenoh callback: hand the payload over to the main loop.
        sub = session.declare_subscriber(keys.gains(LOOP_ID), lambda s: inbox.put(s.payload))
        pub = session.declare_publisher(keys.sample(LOOP_ID))
        end = time.monotonic() + args.seconds
        try:
            while time.monotonic() < end:
                while not inbox.empty():
                    msg = GainsMessage.model_validate_json(inbox.get().to_bytes())
                    if msg.mode == Mode.auto:  # advisory updates are for a human to judge
                        write_gains(msg.kp, msg.ki)
                sp, pv = read_loop()
                pub.put(encode(Sample(t=time.time(), sp=sp, pv=pv, **gains)))
                time.sleep(1.0)
        finally:
            sub.undeclare()  # a callback subscriber left declared hangs the interpreter


if __name__ == "__main__":
    main()
