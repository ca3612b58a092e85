"""FastAPI dependencies, as Annotated aliases the routes take as parameters."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request

from .scheduler import Scheduler
from .store import Store
from .views import load_run


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_scheduler(request: Request) -> Scheduler | None:
    return request.app.state.scheduler


StoreDep = Annotated[Store, Depends(get_store)]
SchedulerDep = Annotated[Scheduler | None, Depends(get_scheduler)]


def not_found(kind: str, ident: str) -> HTTPException:
    return HTTPException(status_code=404, detail=f"no {kind} with id {ident!r}")


def get_run(run_id: str, store: StoreDep) -> dict[str, Any]:
    run = load_run(store, run_id)
    if run is None:
        raise not_found("run", run_id)
    return run


def get_experiment_row(exp_id: str, store: StoreDep) -> dict[str, Any]:
    exp = store.experiment(exp_id)
    if exp is None:
        raise not_found("experiment", exp_id)
    return exp


def require_json(request: Request) -> None:
    """A body that is not declared as JSON is refused (415), not guessed at."""
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype != "application/json" and not ctype.endswith("+json"):
        raise HTTPException(status_code=415, detail="send the body as application/json")


RunDep = Annotated[dict[str, Any], Depends(get_run)]
ExperimentRowDep = Annotated[dict[str, Any], Depends(get_experiment_row)]
JsonBody = Depends(require_json)
