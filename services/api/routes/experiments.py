"""Experiments: one config, seeds, an optional grid and optional arms, expanded into runs;
stopping them, queueing their failed or stopped runs again (retry), their learning
curves per arm and every point of every run as one CSV."""

from __future__ import annotations

import csv
import io
import time
import uuid
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.responses import JSONResponse, Response
from pydantic import AfterValidator

from shared.metrics import CURVE_FIELDS, curve_field_error

from ..deps import (
    AllowedTasks,
    ExperimentRowDep,
    JsonBody,
    SchedulerDep,
    StoreDep,
    not_found,
)
from ..schemas import (
    NOT_FOUND,
    Curves,
    ExperimentCreate,
    ExperimentList,
    ExperimentPublic,
    ExperimentRetryResult,
    ExperimentStopResult,
    Problem,
)
from ..store import CSV_FIELDS
from ..views import curves, load_experiments

router = APIRouter(prefix="/experiments", tags=["experiments"])


def known_metric(name: str) -> str:
    if why := curve_field_error(name):
        raise ValueError(why)
    return name


# The names are checked by known_metric (a 422 that lists them) and listed in the schema.
MetricName = Annotated[
    str,
    AfterValidator(known_metric),
    Query(max_length=64, json_schema_extra={"enum": list(CURVE_FIELDS)}),
]
RunIds = Annotated[
    list[Annotated[str, Query(max_length=200)]] | None,
    Query(max_length=256, description="only these runs (default: every failed or stopped one)"),
]


def new_experiment_id() -> str:
    return "x" + time.strftime("%Y%m%d-%H%M%S-") + uuid.uuid4().hex[:6]


@router.post(
    "",
    status_code=201,
    response_model=ExperimentPublic,
    dependencies=[JsonBody, AllowedTasks],
    responses={
        400: {"description": "the body is not JSON"},
        413: {"model": Problem, "description": "the body is over the size limit (64 KiB)"},
        415: {"model": Problem, "description": "the body is not declared as application/json"},
    },
)
def create_experiment(body: ExperimentCreate, store: StoreDep, scheduler: SchedulerDep):
    """Queue one run per arm, grid point and seed; they start as services become free."""
    exp_id = new_experiment_id()
    expanded = body.expand()
    runs = [
        {
            "id": f"{exp_id}-{i}",
            "seed": r["seed"],
            "arm": r["arm"],
            "point": r["point"],
            "config": r["config"].model_dump(mode="json"),
            "actors": body.actors,
        }
        for i, r in enumerate(expanded)
    ]
    spec = {
        "config": body.base_config(),
        "seeds": body.seed_list(),
        "grid": dict(body.grid.axes()) if body.grid else None,  # nested nulls kept
        "arms": body.arms_spec(),
        "actors": body.actors,
    }
    name = body.name or body.default_name()
    store.create_experiment(exp_id, name, spec, runs)
    created = store.experiment(exp_id)
    assert created is not None  # (created above)
    public = load_experiments(store, [created])[0]  # as this request left it
    if scheduler is not None:
        scheduler.wake()
    return public


@router.get("", response_model=ExperimentList)
def list_experiments(
    store: StoreDep,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
    offset: Annotated[int, Query(ge=0, le=10**9)] = 0,
):
    """Newest first, each with its runs."""
    return {
        "total": store.count_experiments(),
        "experiments": load_experiments(store, store.experiments(limit, offset)),
    }


@router.get("/{exp_id}", response_model=ExperimentPublic, responses=NOT_FOUND)
def get_experiment(exp: ExperimentRowDep, store: StoreDep):
    return load_experiments(store, [exp])[0]


@router.post("/{exp_id}/stop", response_model=ExperimentStopResult, responses=NOT_FOUND)
def stop_experiment(exp: ExperimentRowDep, store: StoreDep, scheduler: SchedulerDep):
    """Stop every queued or running run (idempotent: a second call stops nothing)."""
    stopped = store.stop_experiment(exp["id"], "stopped by user")
    public = load_experiments(store, [exp])[0]  # as this request left it
    if scheduler is not None and stopped:
        scheduler.wake()
    detail = f"stopped {len(stopped)} run(s)" if stopped else "nothing to stop: every run had ended"
    return {
        "changed": bool(stopped),
        "detail": detail,
        "stopped": stopped,
        "experiment": public,
    }


@router.post("/{exp_id}/retry", response_model=ExperimentRetryResult, responses=NOT_FOUND)
def retry_experiment(
    exp: ExperimentRowDep, store: StoreDep, scheduler: SchedulerDep, run: RunIds = None
):
    """Queue the failed and stopped runs again under their ids (completed, queued and
    running runs are left as they are): their points are deleted and `attempts` goes
    up. Idempotent: once they are queued, a second call retries nothing. A running
    experiment is no exception. A retried run keeps its place in the queue (the queue is
    by when its experiment was created, then its index: `Store.runs_with_status`), so it
    starts before later runs still queued."""
    runs = store.runs_of([exp["id"]])[exp["id"]]
    unknown = sorted(set(run or []) - {r["id"] for r in runs})
    if unknown:
        raise not_found(f"run of experiment {exp['id']!r}", ", ".join(unknown))
    retried = store.retry_runs(exp["id"], list(run) if run else None)
    # The response is the state this request left: read before the scheduler is woken,
    # whose next pass says what each queued run waits for in its `reason`.
    public = load_experiments(store, [exp])[0]
    if scheduler is not None and retried:
        scheduler.wake()
    if retried:
        detail = f"queued {len(retried)} run(s) again"
    else:
        counts = ", ".join(f"{v} {k}" for k, v in public["counts"].items())
        detail = f"nothing to retry: no run is failed or stopped ({counts})"
    return {
        "changed": bool(retried),
        "detail": detail,
        "retried": [r["id"] for r in retried],
        "experiment": public,
    }


@router.get("/{exp_id}/curves", response_model=Curves, responses=NOT_FOUND)
def get_curves(
    exp_id: str,
    store: StoreDep,
    metric: Annotated[list[MetricName] | None, Query(max_length=8)] = None,
):
    """Learning curves: per arm (or grid point), the mean over its seeds and mean +- std,
    per episode, each named as its runs' `arm`."""
    out = curves(store, exp_id, metric or ["success_rate", "count1_pct", "steps_per_sec"])
    if out is None:
        raise not_found("experiment", exp_id)
    return out


@router.get("/{exp_id}/figure", responses=NOT_FOUND)
def get_figure(exp: ExperimentRowDep, store: StoreDep, request: Request) -> Response:
    """The figure view's data: the experiment as the report draws it (each arm's smoothed
    mean, band and seeds, controls, claims and their verdicts so far, progress), computed
    by the report's functions (cli/view.py). ETag: 304 while no point was added.

    The ETag is each run's attempt, point count and status. Within an attempt points are
    only added, so its count names what is stored; a retry deletes them and counts the
    attempt up, so a new attempt that reaches its old attempt's count still differs."""
    view = request.app.state.figure_view
    if view is None:
        raise HTTPException(501, "no figure view in this API (start it with `macb serve api`)")
    public = load_experiments(store, [exp])[0]
    etag = (
        '"' + "-".join(f"{r['attempts']}.{r['points']}.{r['status']}" for r in public["runs"]) + '"'
    )
    if request.headers.get("if-none-match") == etag:
        return Response(status_code=304, headers={"ETag": etag})
    points = {r["id"]: store.points(r["id"]) for r in public["runs"]}
    return JSONResponse(view(public, points), headers={"ETag": etag, "Cache-Control": "no-cache"})


@router.get(
    "/{exp_id}/metrics.csv",
    response_class=Response,
    responses={
        200: {"content": {"text/csv": {}}, "description": "one row per point of every run"},
        **NOT_FOUND,
    },
)
def get_experiment_csv(exp: ExperimentRowDep, store: StoreDep):
    """Every stored point of every run, runs in order: `arm`, `seed`, `run` first (so one
    file holds a whole figure), then the columns of GET /runs/{id}/metrics.csv."""
    runs = store.runs_of([exp["id"]])[exp["id"]]
    points = {r["id"]: store.points(r["id"]) for r in runs}
    seen = {k for ps in points.values() for p in ps for k in p}
    extra = sorted(seen - set(CSV_FIELDS) - {"seq", "arm", "seed", "run"})
    buf = io.StringIO()
    writer = csv.DictWriter(
        buf, fieldnames=["arm", "seed", "run", *CSV_FIELDS, *extra], extrasaction="ignore"
    )
    writer.writeheader()
    for r in runs:
        for p in points[r["id"]]:
            writer.writerow({**p, "arm": r["arm"], "seed": r["seed"], "run": r["id"]})
    return Response(
        buf.getvalue(),
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="{exp["id"]}-metrics.csv"'},
    )
