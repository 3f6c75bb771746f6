"""The admin API in a cluster: any member answers for any loop.

A request about one loop (``/loops/{id}`` and below, and ``POST /loops``) that another
member owns is forwarded to that member's API (its ``cluster_url``) with the caller's
headers, bearer token included, and its answer returned as is; the audit history is
read from the shared store by whichever member is asked. A loop whose shard has no live
owner right now (a failover in progress) answers 503 with ``Retry-After``. A forwarded
request carries :data:`FORWARDED`, and is never forwarded again.

``GET /cluster`` shows the members, their loop counts and the loops without an owner.
Without a cluster (an SQLite store) nothing is forwarded and ``/cluster`` says so.
"""

from __future__ import annotations

import re

import httpx
import orjson
from fastapi import APIRouter, FastAPI, Request, Response
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from service.daemon import directory
from service.daemon.shards import shard_of

FORWARDED = "x-pitune-forwarded-by"
FORWARD_TIMEOUT_S = 30.0
_LOOP_PATH = re.compile(r"^/loops/(?P<id>[^/]+)(?P<rest>/.*)?$")
_FROM_STORE = ("/history", "/history.jsonl")
"""Sub-paths any member answers from the shared store."""
_HOP_HEADERS = {"host", "content-length", "connection", "transfer-encoding"}
router = APIRouter(tags=["ops"])


@router.get("/cluster")
def cluster_view(request: Request) -> dict:
    """Members of the cluster sharing this tuner's PostgreSQL store, with their loop
    counts (from the leases in the store)."""
    cluster = request.app.state.tuner.cluster
    if cluster is None:
        return {"self": request.app.state.settings.instance_id, "members": [], "store": "sqlite"}
    return directory.view(cluster)


def _loop_not_here(request: Request) -> bool:
    """The request is about one loop, answered by its owner, which is not in this member's
    engine."""
    match = _LOOP_PATH.match(request.url.path)
    return bool(
        match
        and match["id"] != "bulk"
        and match["rest"] not in _FROM_STORE
        and match["id"] not in request.app.state.tuner.table.slot_of
    )


async def _target(request: Request, cluster) -> tuple[str | None, bool]:
    """(owner's API URL or None, whether the request is about a loop at all)."""
    path = request.url.path
    match = _LOOP_PATH.match(path)
    if match and match["id"] != "bulk":
        if not _loop_not_here(request):
            return None, False
        return await run_in_threadpool(directory.owner_url, cluster.url, match["id"]), True
    if path == "/loops" and request.method == "POST":
        try:
            body = orjson.loads(await request.body())
            shard = shard_of(str(body["id"]), body.get("gateway"))
        except (orjson.JSONDecodeError, KeyError, TypeError, AttributeError):
            return None, False  # the route answers 422
        if cluster.owns(shard):
            return None, False
        return await run_in_threadpool(directory.shard_owner_url, cluster.url, shard), False
    return None, False


def install(app: FastAPI) -> None:
    app.include_router(router)

    @app.middleware("http")
    async def forward(request: Request, call_next):
        tuner = getattr(request.app.state, "tuner", None)
        cluster = None if tuner is None else tuner.cluster
        if cluster is None:
            return await call_next(request)
        if request.headers.get(FORWARDED):  # another member took us for the owner
            url, about_loop = None, _loop_not_here(request)
        else:
            url, about_loop = await _target(request, cluster)
        if url is None or url == cluster.api_url:
            # a stored loop no member has loaded: its owner is changing, or is this member
            # still loading it (a takeover, a NOTIFY not handled yet): not a 404
            if about_loop and await run_in_threadpool(
                directory.stored, cluster.url, request.url.path.split("/")[2]
            ):
                return JSONResponse(
                    {"detail": "the loop's owner is changing (failover); retry shortly"},
                    status_code=503,
                    headers={"Retry-After": str(int(cluster.lease_s))},
                )
            return await call_next(request)
        headers = {k: v for k, v in request.headers.items() if k.lower() not in _HOP_HEADERS}
        headers[FORWARDED] = cluster.member
        async with httpx.AsyncClient(timeout=FORWARD_TIMEOUT_S) as client:
            try:
                answer = await client.request(
                    request.method,
                    url.rstrip("/") + request.url.path,
                    params=request.query_params,
                    headers=headers,
                    content=await request.body(),
                )
            except httpx.HTTPError as exc:
                return JSONResponse(
                    {"detail": f"the loop's owner at {url} did not answer: {exc}"},
                    status_code=503,
                    headers={"Retry-After": "1"},
                )
        kept = {k: v for k, v in answer.headers.items() if k.lower() not in _HOP_HEADERS}
        kept.pop("content-encoding", None)
        return Response(answer.content, status_code=answer.status_code, headers=kept)
