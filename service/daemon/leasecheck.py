"""A cluster member's lease against its Zenoh transport lease, checked at start-up.

The others take a member's leases before they expire only when its Zenoh liveliness
token is gone and the leases went unrenewed for three ticks (docs/deploy.md, Failover):
a crashed process loses its token at once. A paused one (SIGSTOP, a VM frozen) keeps it
until its session's transport lease (``transport/link/tx/lease``, 10 s by default) runs
out, since the peers drop a session that sent nothing for the lease it announced. With a
``cluster_lease_s`` longer than that lease, a pause between the two is read as a death:
the leases are taken at three ticks (18 s of a 30 s lease) while the paused member,
waking, still counts its lease valid (its local clock: 29.5 s) and may publish gains it
committed before the pause after the new owner's first (confirmed: a SIGSTOPped
session's token went after 10.0 s, 20.0 s with a 20,000 ms lease).
"""

from __future__ import annotations

import json

from service.daemon.settings import Settings

LEASE_KEY = "transport/link/tx/lease"
"""The Zenoh config's transport lease, in milliseconds."""


def zenoh_lease_s(settings: Settings) -> float | None:
    """The transport lease of the tuner's Zenoh session, in seconds (None: its config
    does not build; the session's start reports that)."""
    from service.daemon.bus import zenoh_config

    try:
        return json.loads(zenoh_config(settings).get_json(LEASE_KEY)) / 1000.0
    except Exception:  # noqa: BLE001 - any config error is the session's to report
        return None


def lease_mismatch(settings: Settings) -> str | None:
    """Why a cluster member's ``cluster_lease_s`` is unsafe beside its Zenoh transport
    lease (see the module doc), in one line; None when it is not (or no cluster)."""
    if not settings.postgres:
        return None
    zenoh_s = zenoh_lease_s(settings)
    if zenoh_s is None or settings.cluster_lease_s <= zenoh_s:
        return None
    return (
        f"cluster_lease_s ({settings.cluster_lease_s:g} s) is longer than this tuner's Zenoh "
        f"transport lease ({zenoh_s:g} s, {LEASE_KEY}): a member paused longer than the "
        "latter loses its liveliness token and is taken for dead while its own lease still "
        f"runs. Set cluster_lease_s (PITUNE_CLUSTER_LEASE_S) to at most {zenoh_s:g}, or "
        f"{LEASE_KEY} in the Zenoh config (PITUNE_ZENOH_CONFIG) to at least "
        f"{settings.cluster_lease_s * 1000:.0f} (ms)"
    )
