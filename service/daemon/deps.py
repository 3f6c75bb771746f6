"""What the admin API's routers share (:mod:`service.daemon.api`'s loops and operations,
:mod:`service.daemon.hold_api`'s plant-wide hold): the tuner and settings of the app, the
token a change needs, who made a change and its log line."""

from __future__ import annotations

import logging
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.daemon.gate import registering_gateway, token_matches
from service.daemon.settings import Settings
from service.daemon.tuner import Tuner

_bearer = HTTPBearer(auto_error=False, description="PITUNE_API_TOKEN, when set")


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_tuner(request: Request) -> Tuner:
    return request.app.state.tuner


def require_token(
    request: Request,
    settings: Annotated[Settings, Depends(get_settings)],
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """Mutating calls need the bearer token when one is configured (or a gateway's, for
    the registrations the gate let through with it: service.daemon.gate)."""
    given = credentials.credentials if credentials else ""
    if not token_matches(settings, given) and registering_gateway(request.scope) is None:
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing or invalid bearer token",
            headers={"WWW-Authenticate": "Bearer"},
        )


TunerDep = Annotated[Tuner, Depends(get_tuner)]
# Only changes need the token: reads stay open like /healthz and /metrics (the demo and
# dashboards read loops without one); protect reads by binding to loopback or a proxy.
mutating = [Depends(require_token)]


def actor_of(request: Request) -> str:
    """Who makes a REST change, for the audit log: ``gateway:<id>`` with a gateway's token
    (which may only register that gateway's loops), else ``api`` (the admin token, or an
    open API)."""
    gateway = registering_gateway(request.scope)
    return "api" if gateway is None else f"gateway:{gateway}"


def admin_event(tuner: Tuner, request: Request, kind: str, message: str, *args: object) -> None:
    """One INFO line per admin change (rate-limited per kind), with the caller's address
    and, for a gateway's token, the gateway."""
    client = request.client.host if request.client else "?"
    tuner.metrics.events.limiter.log(logging.INFO, kind, message + " via the API from %s as %s",
                                     *args, client, actor_of(request))  # fmt: skip
