"""A minimal reference DCS gateway for pitune: publish samples, apply ``auto`` gains.

It follows docs/protocol.md through :class:`service.gateways.base.Gateway`:

* samples are published with ``CongestionControl.BLOCK`` (never silently dropped);
* a gains message is applied only if its ``(epoch, seq)`` is above the last one taken
  for that loop (duplicates, late arrivals and late messages of a replaced tuner are
  dropped), and only if its mode is ``auto`` (``advisory`` ones are for a human to judge);
* each sample reports ``applied_seq``, the last update written to the PID block (0 once
  an update of the tuner's epoch is taken and none written yet), so the tuner tells a
  gateway lagging behind from an operator's change;
* whenever a tuner's liveliness token appears (tuner started, or this gateway
  (re)connected), it asks the tuner for the loops' state and applies the gains it
  missed meanwhile (same rule); it says when no tuner is up;
* ``--gateway-id ID`` also applies the batched gains (``GainsBatch``) of the loops
  registered with ``"gateway": "ID"``, asks their state in one query (one
  ``StateBatch`` reply), and publishes each scan as one ``SampleBatch`` on
  ``{prefix}/gateways/ID/samples`` (protocol revision 4; per loop while no tuner
  listens there): in a cluster of tuners only the member owning ID's loops receives it;
* it warns when a loop the tuner says is tuning has had no update for more than two RL
  periods (the "update overdue" watchdog), and asks the state again.

Replace the :class:`Dcs` stand-in with your DCS's calls (OPC UA, Modbus, ...). Run it
beside a tuner on this host, or through the compose deployment's router:

    python deploy/examples/dcs_gateway.py --connect tcp/127.0.0.1:7447
    python deploy/examples/dcs_gateway.py --config deploy/zenoh/gateway.json5
"""

import argparse
import logging
import time

import zenoh

from service.gateways.base import Gateway
from service.wire.protocol import Keys, Mode, Sample, is_valid_id
from service.wire.session import session_config

log = logging.getLogger("dcs_gateway")


class Dcs:
    """Stand-in for the DCS: one PID block per loop (here at rest, at fixed gains)."""

    def __init__(self, gains: dict[str, tuple[float, float]]) -> None:
        self.blocks = {loop_id: {"kp": kp, "ki": ki} for loop_id, (kp, ki) in gains.items()}

    def read_loop(self, loop_id: str) -> tuple[float, float]:
        """Setpoint and measurement of a loop."""
        return 55.0, 54.8

    def gains(self, loop_id: str) -> dict[str, float]:
        """The gains in force in the PID block (reported with every sample)."""
        return dict(self.blocks[loop_id])

    def write_gains(self, loop_id: str, kp: float, ki: float) -> None:
        """Write new gains to the PID block (bumpless in the DCS)."""
        self.blocks[loop_id].update(kp=kp, ki=ki)


def scan(gateway: Gateway, dcs: Dcs, asked: set[str]) -> int:
    """One DCS scan: apply the ``auto`` updates received since the last scan (the seq rule
    already applied), then publish a sample per loop. Returns the updates applied.
    ``asked``: the loops whose state was asked again for an overdue update (kept from
    scan to scan: still overdue after the tuner's answer is the alarm)."""
    applied = 0
    for update in gateway.gains():
        if update.mode == Mode.auto:
            dcs.write_gains(update.loop_id, update.kp, update.ki)
            gateway.applied(update)  # reported as applied_seq from the next sample on
            applied += 1
    now = time.time()
    overdue = {loop_id for loop_id in dcs.blocks if gateway.overdue(loop_id, now)}
    if overdue - asked:  # a held step or a cooldown publishes nothing: ask before alarming
        log.info("no update for %s in two RL periods: asking the tuner's state", overdue - asked)
        gateway.query_state()
    if overdue & asked:  # the fresh state still says an update is due: the tuner lags
        log.warning("update overdue for %s", sorted(overdue & asked))
    asked.clear()
    asked.update(overdue)
    samples = {}
    for loop_id in dcs.blocks:
        sp, pv = dcs.read_loop(loop_id)
        samples[loop_id] = Sample(t=now, sp=sp, pv=pv, **dcs.gains(loop_id))
    gateway.publish_scan(samples)  # one batch on the gateway's key with --gateway-id
    return applied


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--connect", default=None, help="Zenoh endpoint of the tuner or router")
    parser.add_argument("--config", default=None, help="Zenoh JSON5 config (auth, router)")
    parser.add_argument(
        "--listen",
        default=None,
        help="Zenoh endpoint to listen on (default without --config: loopback only; the "
        "gateway connects out, and a listener other hosts reach lets them send it gains)",
    )
    parser.add_argument("--prefix", default="pitune", help="key-expression prefix")
    parser.add_argument(
        "--gateway-id", default=None, help="also apply the batched gains of this gateway's loops"
    )
    parser.add_argument("--period", type=float, default=1.0, help="scan period, s")
    parser.add_argument("--seconds", type=float, default=float("inf"), help="stop after this")
    args = parser.parse_args()
    if args.gateway_id is not None and not is_valid_id(args.gateway_id):
        parser.error(f"invalid gateway id {args.gateway_id!r}")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    dcs = Dcs({"LIC-101": (0.5, 0.01)})
    listen = [args.listen] if args.listen else None if args.config else ["tcp/127.0.0.1:0"]
    config = session_config(
        config_file=args.config, connect=[args.connect] if args.connect else None, listen=listen
    )
    session = zenoh.open(config)
    try:
        gateway = Gateway(session, dcs.blocks, Keys(args.prefix), gateway_id=args.gateway_id)
        try:
            end = time.monotonic() + args.seconds
            asked: set[str] = set()
            while time.monotonic() < end:
                scan(gateway, dcs, asked)
                time.sleep(args.period)
        finally:
            gateway.close()  # a callback subscriber left declared hangs the interpreter
    finally:
        session.close()


if __name__ == "__main__":
    main()
