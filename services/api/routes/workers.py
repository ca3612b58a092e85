"""Live services and the API's own health."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException

from ..deps import SchedulerDep
from ..schemas import Health, Problem, Workers

router = APIRouter(tags=["cluster"])

VERSION = "0.1.0"


@router.get(
    "/workers",
    response_model=Workers,
    responses={503: {"model": Problem, "description": "not connected to the bus"}},
)
def get_workers(scheduler: SchedulerDep):
    """Every service with a liveliness token on the bus, with the run it serves."""
    workers = scheduler.workers() if scheduler is not None else None
    if workers is None:
        raise HTTPException(status_code=503, detail="the API is not connected to the bus")
    return {"bus": True, "workers": workers}


@router.get("/health", response_model=Health)
def health(scheduler: SchedulerDep):
    """Always 200 while the API serves; `bus` tells whether it reaches the cluster.
    The only call that needs no token."""
    return {
        "status": "ok",
        "bus": bool(scheduler is not None and scheduler.connected.is_set()),
        "version": VERSION,
    }
