"""FastAPI dependencies, as Annotated aliases the routes take as parameters."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request
from fastapi.exceptions import RequestValidationError

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


def task_names(body: Any) -> list[tuple[tuple[str | int, ...], str]]:
    """(where, name) of every task a POST /experiments body names: the base, the grid's
    values and each arm's."""
    if not isinstance(body, dict):
        return []
    found: list[tuple[tuple[str | int, ...], Any]] = [(("task",), body.get("task"))]
    grid = body.get("grid")
    if isinstance(grid, dict) and isinstance(grid.get("task"), list):
        found += [(("grid", "task", i), t) for i, t in enumerate(grid["task"])]
    arms = body.get("arms")
    for i, arm in enumerate(arms if isinstance(arms, list) else []):
        if isinstance(arm, dict):
            found.append((("arms", i, "task"), arm.get("task")))
    return [(where, t) for where, t in found if isinstance(t, str)]


def module_allowed(module: str, allowed: list[str]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in allowed)


# PettingZoo's own wrappers: every mpe2 and PettingZoo `parallel_env` is one of these
# (`parallel_wrapper_fn`), defined there rather than in the module that names it.
ENV_WRAPPERS = ["pettingzoo.utils.conversions"]


def factory_refusal(task: str, allowed: list[str]) -> str | None:
    """Why the factory a task names may not be called here: one defined outside the
    allowed packages (a function its module imported, e.g. `from os import system`),
    whatever module named it. None when allowed, or when it does not load (the body's
    validation then says why)."""
    from shared.envs.custom_task import TaskError, load_factory

    try:
        factory = load_factory(task)
    except TaskError:
        return None
    defined = getattr(factory, "__module__", None)
    if isinstance(defined, str) and module_allowed(defined, allowed + ENV_WRAPPERS):
        return None
    return (
        f"{task.split(':', 1)[1]} is defined in {defined or 'no module'}, not in a package "
        f"this API may call tasks from ({', '.join(allowed) or 'none'}; MACB_API_TASK_MODULES)"
    )


async def require_allowed_tasks(request: Request) -> None:
    """A custom task (`package.module:factory`) is imported and called in this process
    and on every service to check and run it: only modules under the API's
    `task_modules` (MACB_API_TASK_MODULES) may be named, and the factory must be defined
    in them (`factory_refusal`), so a body cannot make the API call an arbitrary function.
    Refused with 422 naming the field, before the body is validated (which would call
    the factory)."""
    try:
        body = await request.json()
    except ValueError:
        return  # not JSON: the body's own validation says so (400)
    allowed = list(request.app.state.settings.task_modules)
    errors = []
    for where, task in task_names(body):
        module = task.split(":", 1)[0]
        if ":" not in task:
            continue
        if not module_allowed(module, allowed):
            why: str | None = (
                f"module {module!r} is not one this API may import tasks from "
                f"({', '.join(allowed) or 'none'}; MACB_API_TASK_MODULES sets them)"
            )
        else:  # imported (an allowed module), not called: is what it names allowed too?
            why = factory_refusal(task, allowed)
        if why is not None:
            errors.append({"loc": ("body", *where), "msg": why, "type": "value_error"})
    if errors:
        raise RequestValidationError(errors)


RunDep = Annotated[dict[str, Any], Depends(get_run)]
ExperimentRowDep = Annotated[dict[str, Any], Depends(get_experiment_row)]
JsonBody = Depends(require_json)
AllowedTasks = Depends(require_allowed_tasks)
