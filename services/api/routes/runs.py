"""Runs: status, stop, stored metrics (JSON, CSV) and live metrics (server-sent events)."""

from __future__ import annotations

import asyncio
import csv
import io
import json
import time
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Header, Query, Request
from fastapi.responses import Response, StreamingResponse
from starlette.concurrency import run_in_threadpool

from ..deps import RunDep, SchedulerDep, StoreDep, not_found
from ..schemas import NOT_FOUND, MetricsPage, RunPublic, RunStopResult
from ..store import ACTIVE, CSV_FIELDS, Store
from ..views import load_run

router = APIRouter(prefix="/runs", tags=["runs"])

Since = Annotated[int, Query(ge=0, le=2**62, description="only points with a larger seq")]


@router.get("/{run_id}", response_model=RunPublic, responses=NOT_FOUND)
def get_run(run: RunDep):
    """Config, status (queued, running, completed, stopped, failed), progress, services."""
    return run


@router.post("/{run_id}/stop", response_model=RunStopResult, responses=NOT_FOUND)
def stop_run(run: RunDep, store: StoreDep, scheduler: SchedulerDep):
    """Stop a queued or running run; on a run that has ended it is a no-op that says so."""
    if run["status"] not in ACTIVE:
        return {
            "changed": False,
            "detail": f"run already {run['status']}: nothing to stop",
            "run": run,
        }
    # (sent or not as the run stands when stopped: the scheduler may start it meanwhile)
    changed = store.finish(run["id"], "stopped", "stopped by user", stop_sent=None)
    fresh = load_run(store, run["id"])  # as this request left it
    assert fresh is not None  # (runs are never deleted)
    if scheduler is not None:
        scheduler.wake()
    return {
        "changed": changed,
        "detail": "stopped" if changed else f"run already {fresh['status']}: nothing to stop",
        "run": fresh,
    }


@router.get("/{run_id}/metrics", response_model=MetricsPage, responses=NOT_FOUND)
def get_metrics(
    run: RunDep,
    store: StoreDep,
    since: Since = 0,
    limit: Annotated[int, Query(ge=1, le=100_000)] = 10_000,
):
    """Stored metric points in arrival order; poll with `since=next_since` for new ones."""
    text, _, last, attempt, more = store.points_json(run["id"], since, limit)
    # The points are stored as JSON: splice them in instead of decoding 10,000 rows.
    head = json.dumps(
        {
            "run": run["id"],
            "status": run["status"],
            "attempt": attempt,
            "since": since,
            "next_since": last,
        }
    )
    body = f'{head[:-1]}, "more": {json.dumps(more)}, "points": {text}}}'
    return Response(body, media_type="application/json")


@router.get(
    "/{run_id}/metrics.csv",
    response_class=Response,
    responses={200: {"content": {"text/csv": {}}, "description": "one row per point"}, **NOT_FOUND},
)
def get_metrics_csv(run: RunDep, store: StoreDep):
    """The stored points as CSV: macb train's metrics.csv columns, then the services' extras."""
    points = store.points(run["id"])
    extra = sorted({k for p in points for k in p} - set(CSV_FIELDS) - {"seq"})
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=[*CSV_FIELDS, *extra], extrasaction="ignore")
    writer.writeheader()
    writer.writerows(points)
    return Response(
        buf.getvalue(),
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="{run["id"]}-metrics.csv"'},
    )


def _sse(event: str, data: object, ident: int | None = None) -> str:
    head = f"id: {ident}\n" if ident is not None else ""
    return f"{head}event: {event}\ndata: {json.dumps(data, default=str)}\n\n"


async def _events(
    request: Request, store: Store, run_id: str, since: int, poll_s: float
) -> AsyncIterator[str]:
    last_status = None
    last_beat = time.monotonic()
    yield "retry: 1000\n\n"
    while True:
        run = await run_in_threadpool(load_run, store, run_id)
        if run is None:
            return
        # (the points and the attempt they are of read in one statement: a retry
        # deletes the earlier attempt's points in the transaction that counts the new one)
        text, _, _, attempt, _ = await run_in_threadpool(store.points_json, run_id, since, 1000)
        points = json.loads(text)
        for p in points:
            since = p["seq"]
            yield _sse("metric", {**p, "attempt": attempt}, since)
        if run["attempts"] != attempt:  # a retry between the two reads: the status
            await asyncio.sleep(poll_s)  # read is of the attempt before; read both again
            continue
        said = {"status": run["status"], "reason": run["reason"]}
        status = (run["status"], run["reason"], run["progress"]["trained_episodes"], attempt)
        if status != last_status:
            skipped_running = (
                last_status is not None
                and last_status[0] == "queued"
                and run["started"]
                and run["status"] not in ACTIVE
            )
            if skipped_running:
                # Started and ended between two polls (a short run): still say that it
                # ran, so every client sees queued -> running -> the end, in order.
                ran = {"status": "running", "reason": None, "progress": None, "attempt": attempt}
                yield _sse("status", ran)
            last_status = status
            yield _sse("status", {**said, "progress": run["progress"], "attempt": attempt})
        if run["status"] not in ACTIVE and not points:
            # Final, and every stored point has gone out: say so and end the stream.
            yield _sse("end", {**said, "seq": since, "attempt": attempt})
            return
        if points:
            continue
        if await request.is_disconnected():
            return
        if time.monotonic() - last_beat > 10:
            last_beat = time.monotonic()
            yield ": keep-alive\n\n"
        await asyncio.sleep(poll_s)


@router.get(
    "/{run_id}/events",
    response_class=StreamingResponse,
    responses={
        200: {"content": {"text/event-stream": {}}, "description": "an SSE stream"},
        **NOT_FOUND,
    },
)
async def run_events(
    run_id: str,
    request: Request,
    store: StoreDep,
    since: Since = 0,
    # The seq of the last event seen (ASCII digits: str.isdigit takes '²' too).
    last_event_id: Annotated[str | None, Header(pattern=r"^[0-9]{1,19}$")] = None,
):
    """Server-sent events: `metric` (one per point, id = its seq), `status` on each
    change (as polled; a run seen queued and then ended also gets its `running`, with
    progress null), and `end` once the run has ended and every point has been sent.
    Each names the run's `attempt` it is of: a retry (a new attempt, its points numbered
    on) deletes the earlier attempt's points, and its own start again from the first
    episode. Resume with `since` or the Last-Event-ID header."""
    run = await run_in_threadpool(load_run, store, run_id)
    if run is None:
        raise not_found("run", run_id)
    if last_event_id:
        since = max(since, min(int(last_event_id), 2**62))  # SQLite's integers are 64-bit
    poll_s = request.app.state.settings.sse_poll_s
    return StreamingResponse(
        _events(request, store, run_id, since, poll_s),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
