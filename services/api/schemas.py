"""Request and response schemas of the API.

`ExperimentCreate` is the body of POST /experiments: every key of the run config
(`shared.config.TrainConfig`'s fields, reused as they are, so the API and
`macb train` can never disagree on a key, a default or a limit), plus `seeds`, an
optional `grid` over beta and k, an optional `name` and `actors` per run. Unknown
keys are refused, like in a config file.
"""

from __future__ import annotations

import copy
import itertools
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model, model_validator

from shared.config import TrainConfig, format_errors

MAX_RUNS = 256  # seeds x grid points in one experiment

Seed = Annotated[int, *TrainConfig.model_fields["seed"].metadata]
Beta = Annotated[float, *TrainConfig.model_fields["beta"].metadata]
K = Annotated[int, *TrainConfig.model_fields["k"].metadata]


class Grid(BaseModel):
    """Values to sweep; each run takes one combination (the product of the lists)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    beta: list[Beta] | None = Field(None, min_length=1, max_length=32, description="beta values")
    k: list[K] | None = Field(None, min_length=1, max_length=32, description="k values (bits)")

    def points(self) -> list[dict[str, Any]]:
        axes = [(name, values) for name, values in (("beta", self.beta), ("k", self.k)) if values]
        return [
            dict(zip([a for a, _ in axes], combo, strict=True))
            for combo in itertools.product(*(v for _, v in axes))
        ]


class _ExperimentFields(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    name: str | None = Field(
        None, min_length=1, max_length=200, pattern=r"^[^\x00-\x1f\x7f]*$", description="a label"
    )
    seeds: list[Seed] | None = Field(
        None,
        min_length=1,
        max_length=64,
        description="one run per seed (and grid point); default: [seed]",
    )
    grid: Grid | None = Field(None, description='e.g. {"beta": [0.2, 0.8], "k": [64, 512]}')
    actors: int = Field(1, ge=1, le=16, description="actor services per run")

    # ------------------------------------------------------------ expansion
    def config_part(self) -> dict[str, Any]:
        return {name: getattr(self, name) for name in TrainConfig.model_fields}

    def seed_list(self) -> list[int]:
        return list(self.seeds) if self.seeds is not None else [self.seed]  # type: ignore[attr-defined]

    def expand(self) -> list[dict[str, Any]]:
        """One {seed, point, config} per run: grid points outer, seeds inner."""
        base = self.config_part()
        points = self.grid.points() if self.grid else [{}]
        out = []
        for point in points:
            for seed in self.seed_list():
                config = TrainConfig.model_validate({**base, **point, "seed": seed})
                out.append({"seed": seed, "point": point, "config": config})
        return out

    @model_validator(mode="after")
    def _check(self) -> _ExperimentFields:
        if self.seeds is not None and "seed" in self.model_fields_set:
            raise ValueError("seed: give either seed or seeds (a list), not both")
        if self.seeds is not None and len(set(self.seeds)) != len(self.seeds):
            raise ValueError("seeds: a seed is repeated")
        n_points = len(self.grid.points()) if self.grid else 1
        if n_points * len(self.seed_list()) > MAX_RUNS:
            raise ValueError(f"seeds x grid: at most {MAX_RUNS} runs in one experiment")
        try:
            self.expand()  # cross-field rules of the config (task/algo, ...)
        except ValidationError as err:
            raise ValueError(format_errors(err)) from None
        return self


def _config_fields() -> dict[str, Any]:
    return {
        name: (field.annotation, copy.deepcopy(field))
        for name, field in TrainConfig.model_fields.items()
    }


ExperimentCreate = create_model(
    "ExperimentCreate",
    __base__=_ExperimentFields,
    __doc__="An experiment: a run config (the keys of `macb train`), seeds and an "
    "optional grid over beta and k; it expands into one run per seed and grid point.",
    **_config_fields(),
)

Status = Literal["queued", "running", "completed", "stopped", "failed"]


class Progress(BaseModel):
    episode: int = Field(description="the last evaluation point stored")
    episodes: int = Field(description="training episodes of the run")
    fraction: float
    trained_episodes: int = Field(0, description="episodes the learner has ingested")


class RunPublic(BaseModel):
    id: str
    experiment_id: str
    index: int
    seed: int
    point: dict[str, Any] = Field(description="the grid point of this run")
    config: dict[str, Any]
    actors: int
    status: Status
    reason: str | None = Field(None, description="why it failed or stopped, or what it waits for")
    created: datetime
    started: datetime | None = None
    ended: datetime | None = None
    progress: Progress
    points: int = Field(description="metric points stored")
    assign: dict[str, Any] | None = Field(None, description="the services serving it")
    services: dict[str, Any] = Field(description="each service's last status for this run")
    live: dict[str, Any] = Field(description="latest stats per source (learner, counter, ...)")


class ExperimentPublic(BaseModel):
    id: str
    name: str
    created: datetime
    status: Status
    counts: dict[str, int] = Field(description="runs per status")
    config: dict[str, Any] = Field(description="the base config (before seeds and grid)")
    seeds: list[int]
    grid: dict[str, Any] | None
    actors: int
    runs: list[RunPublic]


class ExperimentList(BaseModel):
    total: int
    experiments: list[ExperimentPublic]


class RunStopResult(BaseModel):
    changed: bool = Field(description="false: the run had ended already (a no-op)")
    detail: str
    run: RunPublic


class ExperimentStopResult(BaseModel):
    changed: bool
    detail: str
    stopped: list[str] = Field(description="ids of the runs this call stopped")
    experiment: ExperimentPublic


class MetricsPage(BaseModel):
    run: str
    status: Status
    since: int
    next_since: int = Field(description="pass as `since` to get only newer points")
    more: bool = Field(description="true: more points than `limit` remain after these")
    points: list[dict[str, Any]] = Field(
        description="metric rows with their `seq`: episode, env_steps, success_rate, ..."
    )


class Curve(BaseModel):
    label: str
    point: dict[str, Any]
    runs: list[str]
    episode: list[int]
    mean: list[float]
    std: list[float]
    lo: list[float]
    hi: list[float]
    n: list[int]


class Curves(BaseModel):
    experiment: str
    name: str
    band: str = Field(description="what lo/hi are: mean - std and mean + std over seeds")
    metrics: dict[str, list[Curve]]


class Worker(BaseModel):
    id: str
    role: str
    run: str | None = None
    runs: list[str] = []
    rejects_total: int = 0
    answers: bool = Field(description="false: alive (liveliness token) but not answering info")


class Workers(BaseModel):
    bus: bool = Field(description="whether the API is connected to the bus")
    workers: list[Worker]


class Problem(BaseModel):
    detail: str


NOT_FOUND: dict[int | str, dict[str, Any]] = {404: {"model": Problem, "description": "unknown id"}}


class Health(BaseModel):
    status: Literal["ok"]
    bus: bool
    version: str
