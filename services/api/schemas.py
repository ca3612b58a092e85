"""Request and response schemas of the API.

`ExperimentCreate` is the body of POST /experiments: every key of the run config
(`shared.config.TrainConfig`'s fields, reused as they are, so the API and
`macb train` can never disagree on a key, a default or a limit), plus `seeds`, an
optional `grid` (value lists over any config key but the seed), optional named
`arms` (partial configs over the base), an optional `name` and `actors` per run.
Unknown keys are refused, like in a config file. Each run's whole config is checked
when the experiment is created, so a grid point or arm that makes an invalid
combination is refused, named, before anything is stored.
"""

from __future__ import annotations

import copy
import itertools
import math
import types
from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    create_model,
    field_validator,
    model_validator,
)
from pydantic.config import JsonDict

from shared.config import TrainConfig, actors_error, format_errors, profile_preset

from .naming import point_name, run_name

MAX_RUNS = 256  # arms x grid points x seeds in one experiment
MAX_VALUES = 32  # values of one grid key
MAX_ARMS = 32

Seed = Annotated[int, *TrainConfig.model_fields["seed"].metadata]

# Keys an arm or a grid may not set: seeds are their own list, crossed with both.
SEED_KEYS = ("seed", "seeds")
SEED_MSG = (
    "seeds are not a grid or arm key: list them in `seeds` "
    "(every arm and grid point runs with every seed)"
)
NAME_PATTERN = r"^[^\x00-\x1f\x7f]*$"


def _value_type(name: str) -> Any:
    """A config field's type with its limits, for one value of a grid list or an arm."""
    field = TrainConfig.model_fields[name]
    return Annotated[field.annotation, *field.metadata] if field.metadata else field.annotation


def _plain(value: Any) -> Any:
    """A key's value as JSON has it: a nested config model (count_sketch) as its map."""
    return value.model_dump(mode="json") if isinstance(value, BaseModel) else value


def _varied_keys() -> list[str]:
    return [name for name in TrainConfig.model_fields if name not in SEED_KEYS]


class _GridBase(BaseModel):
    """Values to sweep; each run takes one combination (the product of the lists)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @field_validator("*")
    @classmethod
    def _distinct(cls, values: list[Any] | None) -> list[Any] | None:
        if values is not None and len({repr(v) for v in values}) != len(values):
            raise ValueError("a value is repeated")
        return values

    def axes(self) -> list[tuple[str, list[Any]]]:
        """(key, values) of every key swept, in config-field order."""
        return [
            (name, [_plain(x) for x in v])
            for name in type(self).model_fields
            if (v := getattr(self, name))
        ]

    def size(self) -> int:
        """How many points, without building them (a large product must not be built)."""
        return math.prod(len(values) for _, values in self.axes())

    def points(self) -> list[dict[str, Any]]:
        axes = self.axes()
        return [
            dict(zip([a for a, _ in axes], combo, strict=True))
            for combo in itertools.product(*(v for _, v in axes))
        ]


# A field's type is known only here, at import: list[that type] is spelled as the
# GenericAlias it is, and the fields go in as a map of Any (create_model's own typing).
_GRID_FIELDS: dict[str, Any] = {
    name: (
        types.GenericAlias(list, (_value_type(name),)) | None,
        Field(
            None,
            min_length=1,
            max_length=MAX_VALUES,
            description=f"values of {name}"
            + (f": {d}" if (d := TrainConfig.model_fields[name].description) else ""),
        ),
    )
    for name in _varied_keys()
}
Grid = create_model(
    "Grid",
    __base__=_GridBase,
    __doc__="Values to sweep over any config key but the seed; each run takes one "
    "combination (the product of the lists). A point's name is `key=value,...`.",
    **_GRID_FIELDS,
)


class _ArmBase(BaseModel):
    """A named partial config over the experiment's base config."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    name: str = Field(
        min_length=1, max_length=100, pattern=NAME_PATTERN, description="its name in legends"
    )

    def overrides(self) -> dict[str, Any]:
        """The keys this arm sets (in config-field order), with their values."""
        fields = [n for n in type(self).model_fields if n != "name"]
        return {n: _plain(getattr(self, n)) for n in fields if n in self.model_fields_set}


_ARM_FIELDS: dict[str, Any] = {
    name: (_value_type(name), Field(None, description=TrainConfig.model_fields[name].description))
    for name in _varied_keys()
}
Arm = create_model(
    "Arm",
    __base__=_ArmBase,
    __doc__="An arm: a `name` and the config keys it sets over the base config (any "
    'key but the seed), e.g. {"name": "control", "explore": "constant"}.',
    **_ARM_FIELDS,
)


# `seed` and a list of `seeds` exclude each other (`_check` refuses the pair): the
# schema says so too, so that a client generated from it does not send both.
SEED_OR_SEEDS: JsonDict = {
    "not": {"required": ["seed", "seeds"], "properties": {"seeds": {"type": "array"}}}
}


class _ExperimentFields(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, json_schema_extra=SEED_OR_SEEDS)

    name: str | None = Field(
        None, min_length=1, max_length=200, pattern=NAME_PATTERN, description="a label"
    )
    seeds: list[Seed] | None = Field(
        None,
        min_length=1,
        max_length=64,
        description="one run per seed (and arm and grid point); default: [seed]. Not "
        "with `seed`: give one or the other",
    )
    grid: Grid | None = Field(
        None, description='e.g. {"explore": ["none", "cen-macb"], "beta": [0.2, 0.8]}'
    )
    arms: list[Arm] | None = Field(
        None,
        min_length=1,
        max_length=MAX_ARMS,
        description='named partial configs, e.g. [{"name": "cen-macb", "explore": "cen-macb"}, '
        '{"name": "control", "explore": "constant"}]; crossed with the grid and the seeds',
    )
    actors: int = Field(1, ge=1, le=16, description="actor services per run")

    # ------------------------------------------------------------ expansion
    def config_part(self) -> dict[str, Any]:
        """The config keys the body gives. Only those: a key left out must stay out of
        each run's config as given, so that TrainConfig fills it in, and `profile: thesis`
        can fill in its options (a default passed on explicitly would win over them)."""
        return {
            name: getattr(self, name)
            for name in TrainConfig.model_fields
            if name in self.model_fields_set
        }

    def base_config(self) -> dict[str, Any]:
        """The base config as JSON values (with the defaults and the profile's options of
        keys not given), seed left out. Not checked as a whole: only each run's config
        must be valid (the base may set the task, each arm the algo)."""
        given = self.config_part()
        given = {**profile_preset(getattr(self, "profile", "mpe2"), given), **given}
        config = TrainConfig.model_construct(**given).model_dump(mode="json")
        config.pop("seed")
        return config

    def seed_list(self) -> list[int]:
        if self.seeds is not None:
            return list(self.seeds)
        return [self.seed]  # type: ignore[attr-defined]  # (a config field create_model adds)

    def arm_list(self) -> list[tuple[str | None, dict[str, Any]]]:
        """(name, keys it sets) per arm; one unnamed arm setting nothing without arms."""
        return [(a.name, a.overrides()) for a in self.arms] if self.arms else [(None, {})]

    def arms_spec(self) -> list[dict[str, Any]] | None:
        """The arms as given (name, then the keys each sets), as JSON values."""
        if not self.arms:
            return None
        return [a.model_dump(mode="json", include={"name", *a.overrides()}) for a in self.arms]

    def grid_points(self) -> list[dict[str, Any]]:
        return self.grid.points() if self.grid else [{}]

    def n_runs(self) -> int:
        points = self.grid.size() if self.grid else 1
        return len(self.arm_list()) * points * len(self.seed_list())

    def cells(self) -> list[dict[str, Any]]:
        """One {arm, index, grid_point, point} per arm and grid point: `point` is every
        key the run sets over the base (its arm's, then its grid point's)."""
        return [
            {"arm": arm, "index": i, "grid_point": gp, "point": {**over, **gp}}
            for i, (arm, over) in enumerate(self.arm_list())
            for gp in self.grid_points()
        ]

    def expand(self) -> list[dict[str, Any]]:
        """One {seed, arm, point, config} per run: arms outer, grid points, seeds inner."""
        base = self.config_part()
        out = []
        for cell in self.cells():
            for seed in self.seed_list():
                config = TrainConfig.model_validate({**base, **cell["point"], "seed": seed})
                name = run_name(cell["arm"], cell["grid_point"], config.model_dump(mode="json"))
                out.append({"seed": seed, "arm": name, "point": cell["point"], "config": config})
        return out

    def default_name(self) -> str:
        """The experiment's name when none is given: its base, or its arms' names."""
        config = self.base_config()
        if not self.arms and not self.grid:
            return f"{config['task']} {config['algo']} {config['explore']}"
        names = dict.fromkeys(r["arm"] for r in self.expand())
        text = f"{config['task']}: {' | '.join(names)}"
        return text if len(text) <= 120 else text[:119] + "…"

    # ------------------------------------------------------------ checks
    @model_validator(mode="before")
    @classmethod
    def _no_seed_axis(cls, data: Any) -> Any:
        """A seed in the grid or an arm is refused by name, not as an unknown key."""
        if not isinstance(data, dict):
            return data
        grid = data.get("grid")
        for key in SEED_KEYS:
            if isinstance(grid, dict) and key in grid:
                raise ValueError(f"grid.{key}: {SEED_MSG}")
        arms = data.get("arms")
        for i, arm in enumerate(arms if isinstance(arms, list) else []):
            for key in SEED_KEYS:
                if isinstance(arm, dict) and key in arm:
                    raise ValueError(f"arms.{i}.{key}: {SEED_MSG}")
        return data

    @field_validator("seeds")
    @classmethod
    def _distinct_seeds(cls, seeds: list[int] | None) -> list[int] | None:
        """On the field, so the error's location is `seeds` (the API's and the CLI's)."""
        if seeds is not None and len(set(seeds)) != len(seeds):
            raise ValueError("a seed is repeated")
        return seeds

    @model_validator(mode="after")
    def _check(self) -> _ExperimentFields:
        if self.seeds is not None and "seed" in self.model_fields_set:
            raise ValueError("seed: give either seed or seeds (a list), not both")
        swept = {key for key, _ in self.grid.axes()} if self.grid else set()
        names: set[str] = set()
        for i, arm in enumerate(self.arms or []):
            if arm.name in names:
                raise ValueError(f"arms.{i}.name: {arm.name!r} names an earlier arm too")
            names.add(arm.name)
            for key in arm.overrides():
                if key in swept:
                    raise ValueError(
                        f"arms.{i}.{key}: the grid sweeps {key} too; set it in the arms "
                        "or in the grid, not both"
                    )
        if self.n_runs() > MAX_RUNS:
            what = "arms x grid x seeds" if self.arms else "seeds x grid"
            raise ValueError(f"{what}: at most {MAX_RUNS} runs in one experiment")
        self._check_cells()
        return self

    def _check_cells(self) -> None:
        """Every arm and grid point must make a valid config with the base (the
        cross-field rules: task/algo, ...); the first invalid one is named."""
        base = {**self.config_part(), "seed": self.seed_list()[0]}
        failures: list[str] = []
        run_names: set[str] = set()
        for cell in self.cells():
            try:
                config = TrainConfig.model_validate({**base, **cell["point"]})
            except ValidationError as err:
                failures.append(self._where(cell) + format_errors(err))
                continue
            if why := actors_error(config, self.actors):
                failures.append(self._where(cell) + why)
                continue
            name = run_name(cell["arm"], cell["grid_point"], config.model_dump(mode="json"))
            if name in run_names:
                raise ValueError(f"arms: two combinations are both named {name!r}; rename an arm")
            run_names.add(name)
        if failures:
            more = len(failures) - 1
            raise ValueError(
                failures[0] + (f" ({more} more combination(s) are invalid too)" if more else "")
            )

    def _where(self, cell: dict[str, Any]) -> str:
        """`grid: point task=simple,algo=dis-maddpg: ` and the like, before the reason."""
        if cell["arm"] is None and not cell["grid_point"]:
            return ""  # no arms, no grid: the base is the run, its errors are its own
        if cell["arm"] is None:
            return f"grid: point {point_name(cell['grid_point'])}: "
        where = f"arms.{cell['index']}: arm {cell['arm']!r}"
        if cell["grid_point"]:
            where += f" with grid point {point_name(cell['grid_point'])}"
        return where + ": "


def _config_fields() -> dict[str, Any]:
    return {
        name: (field.annotation, copy.deepcopy(field))
        for name, field in TrainConfig.model_fields.items()
    }


ExperimentCreate = create_model(
    "ExperimentCreate",
    __base__=_ExperimentFields,
    __doc__="An experiment: a run config (the keys of `macb train`), seeds, an optional "
    "grid over any config key and optional named arms; it expands into one run per arm, "
    "grid point and seed.",
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
    arm: str = Field(
        description="its arm's name: the arm's `name`, the grid point's `key=value,...`, "
        "both, or `algo + explore` for an experiment with neither"
    )
    point: dict[str, Any] = Field(
        description="the keys this run sets over the base config: its arm's and its grid point's"
    )
    config: dict[str, Any]
    actors: int
    status: Status
    reason: str | None = Field(None, description="why it failed or stopped, or what it waits for")
    created: datetime
    started: datetime | None = None
    ended: datetime | None = None
    progress: Progress
    points: int = Field(description="metric points stored")
    attempts: int = Field(
        1, description="how often it was queued: 1, plus one per retry (its points then go)"
    )
    assign: dict[str, Any] | None = Field(None, description="the services serving it")
    services: dict[str, Any] = Field(description="each service's last status for this run")
    live: dict[str, Any] = Field(
        description="latest stats per source (learner, counter, ...; provenance: what the "
        "learner runs on, docs/reliability.md)"
    )


class ExperimentPublic(BaseModel):
    id: str
    name: str
    created: datetime
    status: Status
    counts: dict[str, int] = Field(description="runs per status")
    config: dict[str, Any] = Field(description="the base config (before seeds, arms and grid)")
    seeds: list[int]
    grid: dict[str, Any] | None
    arms: list[dict[str, Any]] | None = Field(None, description="the arms as given, or null")
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


class ExperimentRetryResult(BaseModel):
    changed: bool = Field(description="false: no run was failed or stopped (a no-op)")
    detail: str
    retried: list[str] = Field(description="ids of the runs queued again by this call")
    experiment: ExperimentPublic


class MetricsPage(BaseModel):
    run: str
    status: Status
    attempt: int = Field(
        description="the run's attempt, read with the points: every point here is of it"
        " (a retry deletes the earlier attempts' points)"
    )
    since: int
    next_since: int = Field(description="pass as `since` to get only newer points")
    more: bool = Field(description="true: more points than `limit` remain after these")
    points: list[dict[str, Any]] = Field(
        description="metric rows with their `seq`: episode, env_steps, success_rate, ..."
    )


class Curve(BaseModel):
    """One arm (or grid point): per episode, the mean over its seeds and the band."""

    name: str = Field(description="the arm's name (what its runs carry as `arm`)")
    label: str = Field(description="the legend text: the same as `name`")
    point: dict[str, Any] = Field(description="the keys its runs set over the base config")
    explore: str | None = Field(
        None,
        description="its runs' `explore`; none and constant count nothing, so their curves "
        "of the count metrics (count1_pct, sampled_count1_pct, table_size, "
        "counted_transitions) are empty",
    )
    runs: list[str]
    seeds: list[int] = Field(description="the seed of each run, in the order of `runs`")
    episode: list[int]
    mean: list[float]
    std: list[float] = Field(description="standard deviation over seeds (population, ddof 0)")
    lo: list[float] = Field(description="mean - std")
    hi: list[float] = Field(description="mean + std")
    n: list[int] = Field(description="how many seeds have a point at this episode")


class Curves(BaseModel):
    experiment: str
    name: str
    band: str = Field(description="what lo/hi are: mean - std and mean + std over seeds")
    metrics: dict[str, list[Curve]] = Field(description="per metric, one curve per arm")


class Worker(BaseModel):
    id: str
    role: str
    run: str | None = None
    runs: list[str] = []
    rejects_total: int = 0
    restarts: int = 0  # times `macb up`'s supervisor restarted it
    node: str | None = Field(None, description="the node it runs on (its counter serves its runs)")
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
