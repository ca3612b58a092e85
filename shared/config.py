"""The experiment config: one schema for `macb train`, config files and the API.

Defaults are the thesis's appendix A settings. Invalid configs are refused before
anything runs, naming the field and the reason (pydantic does the work; unknown
keys are errors, so a misspelt key never silently falls back to a default).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from shared.core.counting import SKETCH_MAX_CELLS, SKETCH_MAX_DEPTH, SKETCH_MAX_WIDTH

MULTI_AGENT_TASKS = ("spread", "speaker_listener")
BUILTIN_TASKS = ("simple", *MULTI_AGENT_TASKS)
# Options that only the built-in particle tasks have (their worlds' sizes, rewards,
# observations and physics); a custom task refuses a value other than the default.
WORLD_OPTIONS = ("cover", "landmark_size", "pad_obs", "comm_obs", "integrator")
# The explore modes that count transitions (a table, a count-1 share, a bonus that can
# fall); `constant` pays the bonus on every reward and counts nothing.
COUNTING_EXPLORE = ("dis-macb", "cen-macb")


def _not_a_bool(value: Any) -> Any:
    """A number field refuses true and false (lax pydantic reads them as 1 and 0: a YAML
    `threads: yes` or a JSON `"episodes": true` ran as 1)."""
    if isinstance(value, bool):
        raise ValueError(f"a number, not {str(value).lower()}")
    return value


Int = Annotated[int, BeforeValidator(_not_a_bool)]
Float = Annotated[float, BeforeValidator(_not_a_bool)]


class BetaSchedule(BaseModel):
    """How the bonus scale moves from `beta` to `end` over `horizon` episodes or steps
    (beyond the thesis: its §7 suggests a decaying beta for Cen-MACB's fall after it
    converges). `constant` keeps `beta` throughout: the thesis's method, bit for bit."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    kind: Literal["constant", "linear", "exponential"] = Field(
        "constant",
        description="constant (beta throughout), linear or exponential (geometric) from "
        "beta to end over horizon, end after it",
    )
    end: Float | None = Field(None, ge=0.0, le=100.0, description="beta at the horizon and after")
    horizon: Int | None = Field(None, ge=1, le=10**12, description="episodes or steps to reach end")
    unit: Literal["episodes", "steps"] = Field(
        "episodes", description="what horizon counts: training episodes or transitions"
    )

    @model_validator(mode="after")
    def _check(self) -> BetaSchedule:
        if self.kind == "constant":
            for name in ("end", "horizon"):
                if getattr(self, name) is not None:
                    raise ValueError(f"{name}: a constant schedule keeps beta; give kind "
                                     "linear or exponential to move it")  # fmt: skip
        else:
            for name in ("end", "horizon"):
                if getattr(self, name) is None:
                    raise ValueError(f"{name}: kind {self.kind} needs end and horizon")
            if self.kind == "exponential" and self.end == 0:
                raise ValueError("end: an exponential schedule never reaches 0; give end > 0 "
                                 "or kind linear")  # fmt: skip
        return self

    def at(self, beta: float, progress: int) -> float:
        """The beta in force `progress` episodes or steps into the run."""
        if self.kind == "constant" or self.horizon is None or self.end is None:
            return beta
        if progress >= self.horizon:
            return self.end
        f = max(progress, 0) / self.horizon
        if self.kind == "linear":
            return beta + (self.end - beta) * f
        return float(beta * (self.end / beta) ** f)


class EarlyStop(BaseModel):
    """When a run ends before its episodes, read on its evaluation points (beyond the
    thesis: its §6.3 and §7 suggest early stopping for Cen-MACB's fall after it
    converges). The best point's weights are kept beside the last (best.pt)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    rule: Literal["success_at_least", "no_improvement"] = Field(
        ...,
        description="success_at_least: the (smoothed) success rate >= threshold at "
        "patience points in a row; no_improvement: the smoothed success rate has not "
        "beaten its best for patience points",
    )
    threshold: Float | None = Field(
        None, ge=0.0, le=1.0, description="success_at_least: the success rate to reach"
    )
    patience: Int = Field(1, ge=1, le=100_000, description="evaluation points the rule needs")
    smooth: Int = Field(
        1, ge=1, le=10_000, description="points in the moving mean of the success rate (1: raw)"
    )
    min_delta: Float = Field(
        0.0, ge=0.0, le=1.0, description="no_improvement: how much above its best counts"
    )

    @model_validator(mode="after")
    def _check(self) -> EarlyStop:
        if self.rule == "success_at_least" and self.threshold is None:
            raise ValueError("threshold: rule success_at_least needs a threshold")
        if self.rule == "no_improvement" and self.threshold is not None:
            raise ValueError("threshold: rule no_improvement has none (min_delta says how "
                             "much is better)")  # fmt: skip
        return self


class CountSketchConfig(BaseModel):
    """`count_sketch`: count in a count-min sketch of fixed size instead of the exact
    table (shared/core/counting.py, CountSketch). Its size is `width` x `depth` cells,
    or what fits in `memory_mb` at `depth`; each table of the run gets one that size."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    width: Int | None = Field(
        None,
        ge=1,
        le=SKETCH_MAX_WIDTH,
        description="cells per row: estimate <= true + (e / width) * N with probability "
        ">= 1 - exp(-depth) (N: transitions counted); give width or memory_mb",
    )
    depth: Int = Field(4, ge=1, le=SKETCH_MAX_DEPTH, description="rows (hash functions)")
    memory_mb: Float | None = Field(
        None,
        gt=0.0,
        le=8192.0,
        description="MiB of 4-byte cells per table: width = memory_mb * 2^20 / (4 * depth)",
    )
    conservative: bool = Field(
        True,
        description="conservative update (raise a key's cells only to its new estimate): "
        "the same bound, smaller overestimates; false: every cell + 1 (the plain sketch)",
    )

    @model_validator(mode="after")
    def _one_size(self) -> CountSketchConfig:
        if (self.width is None) == (self.memory_mb is None):
            raise ValueError("give width or memory_mb (one of them) for the sketch's size")
        if self.columns < 1:
            raise ValueError(
                f"memory_mb {self.memory_mb} holds not one column of {self.depth} 4-byte cells"
            )
        if self.columns > SKETCH_MAX_WIDTH:
            raise ValueError(f"memory_mb {self.memory_mb} gives a width over {SKETCH_MAX_WIDTH}")
        if self.columns * self.depth > SKETCH_MAX_CELLS:
            raise ValueError(
                f"width {self.columns} x depth {self.depth} is over {SKETCH_MAX_CELLS} cells"
            )
        return self

    @property
    def columns(self) -> int:
        """The width in force: given, or what memory_mb holds at this depth."""
        if self.width is not None:
            return self.width
        assert self.memory_mb is not None
        return int(self.memory_mb * 2**20) // (4 * self.depth)


class TrainConfig(BaseModel):
    """One training run. Field docs appear in `macb train --help` and the API schema."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    task: str = Field(
        "speaker_listener",
        max_length=300,
        description="simple (1-agent nav), spread (N-agent nav), speaker_listener, or your "
        "own: package.module:factory returning a PettingZoo ParallelEnv with Box spaces "
        "(docs/tasks.md, 'Your own task')",
    )
    task_kwargs: dict[str, Any] | None = Field(
        None,
        description="a custom task's factory keyword arguments, e.g. "
        "{continuous_actions: true, max_cycles: 25}",
    )
    success_key: str | None = Field(
        None,
        min_length=1,
        max_length=100,
        description="a custom task's info key whose true value marks success at a step "
        "(some agent's info); without it the success rate stays 0",
    )
    agents: Int = Field(2, ge=2, le=8, description="number of agents and landmarks (spread only)")
    algo: Literal["ddpg", "dis-maddpg", "cen-maddpg"] = Field(
        "cen-maddpg", description="ddpg (simple), dis-maddpg or cen-maddpg (multi-agent tasks)"
    )
    explore: Literal["none", "dis-macb", "cen-macb", "constant"] = Field(
        "cen-macb",
        description="count bonus: none, dis-macb (table per agent), cen-macb (joint table), "
        "constant (control arm: bonus beta on every reward, no counting)",
    )
    beta: Float = Field(0.8, ge=0.0, le=100.0, description="bonus scale: r' = r + beta / sqrt(n)")
    beta_schedule: BetaSchedule | None = Field(
        None,
        description="beta moving over the run (beyond the thesis), e.g. {kind: linear, end: "
        "0.1, horizon: 20000, unit: episodes}; none: beta throughout (docs/fidelity.md, B1)",
    )
    k: Int = Field(512, ge=1, le=4096, description="SimHash code length in bits")
    hash: Literal["simhash", "none", "raw"] = Field(
        "simhash",
        description="simhash, none (key = the vector rounded to hash_round decimals, else "
        "2) or raw (key = the vector's float32 bytes: the thesis code's strategy 'None', "
        "its fig. 3 loop)",
    )
    key: Literal["state-action", "state"] = Field(
        "state-action", description="count s||a (state-action) or s only (state)"
    )
    count_sketch: CountSketchConfig | None = Field(
        None,
        description="keep each table's counts in a count-min sketch of fixed memory instead "
        "of the exact table (default: exact), e.g. {width: 1048576, depth: 4} or "
        "{memory_mb: 16}: counts never below the true ones, above by at most (e / width) "
        "x transitions with probability 1 - exp(-depth) (docs/fidelity.md)",
    )
    bonus_at: Literal["sample", "collection"] = Field(
        "sample",
        description="when a transition's bonus is priced: sample (at every sampling, from "
        "the counts then; the thesis text's Alg. 2) or collection (once, when it is "
        "collected and counted, stored with its reward: the thesis code's fig. 3 loop); "
        "collection runs in macb train and run groups (--local), not in the cluster",
    )
    reward: Literal["sparse", "sparse_offset", "dense"] = Field(
        "sparse", description="sparse (thesis), sparse_offset (sparse + 0.7), dense (mpe2's own)"
    )
    episodes: Int = Field(1000, ge=1, le=10**8, description="training episodes")
    episode_len: Int = Field(20, ge=1, le=1000, description="steps per episode")
    seed: Int = Field(0, ge=0, lt=2**31, description="run seed")
    eval_every: Int = Field(
        1, ge=1, le=10**8, description="evaluate after every M training episodes"
    )
    eval_episodes: Int = Field(10, ge=1, le=1000, description="noise-free episodes per evaluation")
    early_stop: EarlyStop | None = Field(
        None,
        description="end the run when a rule holds on its evaluation points (beyond the "
        "thesis), e.g. {rule: success_at_least, threshold: 0.9, patience: 5}; the best "
        "point's weights go to best.pt (docs/fidelity.md, B2)",
    )
    batch_size: Int = Field(100, ge=1, le=100_000)
    buffer_size: Int = Field(1_000_000, ge=1, le=10**9)
    learning_starts: Int = Field(
        100, ge=0, le=10**12, description="transitions collected before updates"
    )
    gamma: Float = Field(0.99, ge=0.0, le=1.0)
    tau: Float = Field(0.005, gt=0.0, le=1.0)
    lr_actor: Float = Field(1e-3, gt=0.0, le=1.0)
    lr_critic: Float = Field(1e-3, gt=0.0, le=1.0)
    hidden: tuple[Int, ...] = Field(
        (400, 300), min_length=1, max_length=16, description="MLP hidden sizes"
    )
    noise_sigma: Float = Field(
        0.1, ge=0.0, le=10.0, description="Gaussian action noise, relative to the half-range"
    )
    time_limit_terminal: bool = Field(
        False,
        description="treat the episode time limit as terminal (the thesis code did); "
        "by default targets bootstrap through it",
    )
    # --- profile: which formulation. Each choice below is also an option of its own, so
    # a user can switch one and measure its effect; docs/fidelity.md has one row each.
    profile: Literal["mpe2", "thesis"] = Field(
        "mpe2",
        description="mpe2: the method as the thesis text states it on mpe2's tasks; "
        "thesis: the thesis's public code wherever it differs (sets the options below "
        "that are not given; docs/fidelity.md)",
    )
    success_terminal: bool = Field(
        False,
        description="a step where the task's success holds is terminal (not bootstrapped) "
        "and the world resets at once, the 20-step window going on (the thesis code)",
    )
    cover: Literal["sum", "landmark"] = Field(
        "sum",
        description="navigation's sparse reward counts a landmark covered within the sum "
        "of agent and landmark sizes (sum), or within the landmark's own size (landmark, "
        "the thesis code); success always uses the sum",
    )
    landmark_size: Float | None = Field(
        None,
        gt=0.0,
        le=1.0,
        description="landmark radius; default: the task's (speaker_listener 0.04 as "
        "mpe2, 0.075 in the thesis code; navigation 0.125; simple 0.05)",
    )
    pad_obs: bool = Field(
        False,
        description="pad every agent's observation with zeros to the largest one "
        "(the thesis code: the speaker's 3 values to 11)",
    )
    comm_obs: bool = Field(
        True,
        description="spread: keep mpe2's always-zero communication slots in each "
        "observation (the thesis code has none)",
    )
    integrator: Literal["position-first", "velocity-first"] = Field(
        "position-first",
        description="world step order: position-first (mpe2: move, then damp and push) "
        "or velocity-first (the thesis code's MPE: damp and push, then move)",
    )
    warmup: Literal["policy", "random"] = Field(
        "policy",
        description="actions while the first learning_starts transitions are collected: "
        "the policy with noise, or uniform random (the thesis code)",
    )
    minibatch: Literal["shared", "per-agent"] = Field(
        "shared",
        description="one minibatch for all agents per update, or one per agent (the "
        "thesis code; Algorithm 1's 'each agent samples')",
    )
    # Strict: `false` is no number of decimals (lax int would read it as 0).
    hash_round: Annotated[Int, Field(strict=True)] | None = Field(
        None,
        ge=0,
        le=8,
        description="round the counted vector to this many decimals before it is keyed "
        "(SimHash or raw bytes; hash none: the key's decimals, 2 when unset) (the thesis "
        "code: 2, for Cen-MACB only, whatever its strategy)",
    )
    same_init: bool = Field(
        False,
        description="agents of the same shape start from identical weights (the thesis "
        "code reseeds torch for each agent)",
    )
    interleave: Literal["async", "lockstep"] = Field(
        "async",
        description="how a cluster run interleaves acting, counting and learning: "
        "lockstep (the thesis's loop, as macb train runs it: each step's action comes "
        "from the current weights, computed by the learner, and the step is counted and "
        "learnt before the next; one actor) or async (actors collect whole episodes with "
        "weights published at episode ends, the learner catches up: faster, not the "
        "thesis's interleaving). macb train and run groups always run the thesis's loop",
    )
    threads: Int = Field(1, ge=1, le=64, description="torch intra-op threads")
    learner_lanes: Literal["auto"] | Annotated[Int, Field(ge=1, le=16)] = Field(
        "auto",
        description="batched learner on the CPU (on a GPU it runs one lane): split each "
        "minibatch into this many row blocks computed in parallel threads (1 torch thread "
        "each); auto: whichever of one thread, two lanes or two torch threads measures "
        "fastest on this machine now (reruns then equal up to float rounding; a fixed "
        "number gives bit-identical reruns)",
    )
    learner_impl: Literal["batched", "reference"] = Field(
        "batched",
        description="batched: all agents in stacked matrix products (fast); "
        "reference: one plain PyTorch update per agent (same math)",
    )
    flush_denormals: bool = Field(
        True,
        description="the learner's updates on the CPU read and make subnormal floats (below "
        "1.2e-38) as 0 (x86 DAZ/FTZ): Adam's first moments of weights with zero gradient "
        "otherwise stay subnormal and slow every update 1.4-1.7x on Intel CPUs "
        "(docs/performance.md, 'Subnormal Adam moments'); false keeps IEEE subnormals, as "
        "the thesis code",
    )
    precision: Literal["fp32", "bf16"] = Field(
        "fp32",
        description="batched learner: the update's matrix products in fp32, or in bf16 with "
        "fp32 accumulation (~2x faster on CPUs with AVX512-BF16/AMX; master weights, Adam, "
        "targets and acting stay fp32; whole runs not shown equivalent to fp32's: "
        "docs/performance.md); without native bf16 the learner runs fp32 and logs a warning",
    )

    device: str = Field(
        "cpu",
        pattern=r"^(cpu|cuda(:[0-9]+)?|xpu(:[0-9]+)?|mps)$",
        description="torch device of the batched learner's networks and updates (cpu, "
        "cuda, cuda:N, xpu, mps); a group's replay rows live there too, acting, sampling "
        "and counting stay on the CPU. A device "
        "this torch build or machine lacks is refused when the learner is built",
    )

    @field_validator("task_kwargs")
    @classmethod
    def _plain_kwargs(cls, kwargs: dict[str, Any] | None) -> dict[str, Any] | None:
        """Refused unless plain data every part can carry (the store's JSON, the UTF-8 of
        HTTP replies, msgpack on the bus): else a body stored by the API would break every
        listing that shows it, and its run's start would fail to encode."""
        if kwargs is not None:
            plain_data(kwargs, "task_kwargs")
        return kwargs

    @field_validator("task")
    @classmethod
    def _task_name(cls, task: str) -> str:
        if task in BUILTIN_TASKS or ":" in task:
            return task
        raise ValueError(
            f"unknown task {task!r}: one of {', '.join(BUILTIN_TASKS)}, or your own as "
            "package.module:factory"
        )

    @model_validator(mode="before")
    @classmethod
    def _apply_profile(cls, data: Any) -> Any:
        """`profile: thesis` fills in the thesis code's choice for every option not given;
        a custom task's reward is its env's own (`dense`) unless given."""
        if isinstance(data, dict) and data.get("profile") == "thesis":
            data = {**profile_preset("thesis", data), **data}
        if isinstance(data, dict) and ":" in str(data.get("task", "")) and "reward" not in data:
            data = {**data, "reward": "dense"}
        return data

    def _check_custom_task(self) -> None:
        """Refuse what a custom task cannot take; import its factory, build one env and
        check its spaces (shared/envs/custom_task.py names the agent and the space)."""
        from shared.envs.custom_task import TaskError
        from shared.envs.tasks import task_spec_for

        for name in WORLD_OPTIONS:
            if getattr(self, name) != type(self).model_fields[name].default:
                raise ValueError(
                    f"{name}: an option of the built-in particle tasks; task {self.task} is "
                    "a custom task"
                )
        if self.reward != "dense":
            raise ValueError(
                f"reward: a custom task's reward is its env's own (the mean over agents, "
                f"reward dense), not {self.reward}"
            )
        try:
            spec = task_spec_for(self)
        except TaskError as err:
            text = str(err)
            raise ValueError(text if text.startswith("success_key:") else f"task: {text}") from None
        if self.algo == "ddpg" and spec.n_agents != 1:
            raise ValueError(
                f"algo ddpg trains one agent; task {self.task} has {spec.n_agents}: use "
                "dis-maddpg or cen-maddpg"
            )
        if self.algo != "ddpg" and spec.n_agents < 2:
            raise ValueError(f"algo {self.algo} needs several agents; task {self.task} has one")

    @model_validator(mode="after")
    def _check_combination(self) -> TrainConfig:
        if ":" in self.task:
            self._check_custom_task()
        else:
            for name in ("task_kwargs", "success_key"):
                if getattr(self, name) is not None:
                    raise ValueError(
                        f"{name}: only for a custom task (package.module:factory), not "
                        f"task {self.task}"
                    )
        if self.task == "simple" and self.algo != "ddpg":
            raise ValueError(
                f"algo {self.algo} needs several agents; task simple has one: use ddpg"
            )
        if self.task in MULTI_AGENT_TASKS and self.algo == "ddpg":
            raise ValueError(f"algo ddpg trains one agent; task {self.task} has several")
        if any(not 1 <= h <= 65_536 for h in self.hidden):
            raise ValueError("hidden sizes must be from 1 to 65536")
        if self.device != "cpu" and self.learner_impl == "reference":
            raise ValueError(
                f"device {self.device} needs learner_impl batched; learner_impl reference "
                "is the CPU definition the batched learner is checked against"
            )
        s = self.beta_schedule
        if s is not None and s.kind == "exponential" and self.beta == 0:
            raise ValueError(
                "beta_schedule: an exponential schedule from beta 0 stays 0; give beta > 0 "
                "or kind linear"
            )
        if s is not None and s.kind != "constant" and self.explore == "none":
            raise ValueError("beta_schedule: explore none pays no bonus to schedule")
        if self.precision == "bf16" and self.learner_impl == "reference":
            raise ValueError(
                "precision bf16 needs learner_impl batched; learner_impl reference is the "
                "fp32 definition the batched learner is checked against"
            )
        return self

    def beta_at(self, env_steps: int) -> float:
        """The beta in force for the run's `env_steps`-th transition (1-based: the one
        just collected, and the updates it owes): every place that prices the bonus
        asks this. Episodes are the ones completed before that transition's."""
        s = self.beta_schedule
        if s is None or s.kind == "constant":
            return self.beta
        progress = env_steps if s.unit == "steps" else max(env_steps - 1, 0) // self.episode_len
        return s.at(self.beta, progress)

    @property
    def counts(self) -> bool:
        """The run counts its transitions (Dis- or Cen-MACB): a table, a bonus that falls."""
        return self.explore in COUNTING_EXPLORE

    @property
    def n_agents(self) -> int:
        if ":" in self.task:  # the env's agents (its spec is cached once checked)
            from shared.envs.tasks import task_spec_for

            return task_spec_for(self).n_agents
        return {"simple": 1, "speaker_listener": 2}.get(self.task, self.agents)


# The options a profile sets, and the value each takes under `profile: thesis` (where the
# thesis's public code differs from the method as stated on mpe2; docs/fidelity.md).
PROFILE_OPTIONS = (
    "time_limit_terminal",
    "success_terminal",
    "cover",
    "landmark_size",
    "pad_obs",
    "comm_obs",
    "integrator",
    "warmup",
    "minibatch",
    "hash_round",
    "same_init",
    "interleave",
)


def profile_preset(profile: str, data: dict[str, Any]) -> dict[str, Any]:
    """The option values `profile` sets for a config given as `data` (some depend on its
    task and exploration); mpe2 sets the defaults."""
    if profile != "thesis":
        return {}
    task = data.get("task", TrainConfig.model_fields["task"].default)
    explore = data.get("explore", TrainConfig.model_fields["explore"].default)
    if ":" in str(task):  # a custom task: the thesis code's choices that are not its world's
        return {
            "time_limit_terminal": True,
            "success_terminal": True,
            "warmup": "random",
            "minibatch": "per-agent",
            "hash_round": 2 if explore == "cen-macb" else None,
            "same_init": True,
            "interleave": "lockstep",
        }
    return {
        "time_limit_terminal": True,
        "success_terminal": True,
        "cover": "landmark",
        "landmark_size": 0.075 if task == "speaker_listener" else None,
        "pad_obs": True,
        "comm_obs": False,
        "integrator": "velocity-first",
        "warmup": "random",
        "minibatch": "per-agent",
        "hash_round": 2 if explore == "cen-macb" else None,
        "same_init": True,
        "interleave": "lockstep",
    }


def actors_error(config: TrainConfig, actors: int) -> str | None:
    """Why a run of `config` cannot have `actors` actors, or None. Lockstep is the
    thesis's loop, one environment: every entry point (API, CLI, `start_run`, the
    learner) refuses more with this one message."""
    if config.interleave == "lockstep" and actors != 1:
        return (
            f"actors: interleave lockstep (the thesis's loop; profile thesis's default) runs "
            f"one actor, not {actors}; set interleave: async for several"
        )
    return None


# Fields that are a model of their own: an error's second part names their own field
# (`beta_schedule.end: ...`).
NESTED_FIELDS = frozenset({"count_sketch", "beta_schedule", "early_stop"})


class ConfigError(ValueError):
    """A config refused before anything runs; the message names each field and reason."""


def format_errors(err: ValidationError) -> str:
    """'field: reason; ...'. A field that may take one of several types (learner_lanes:
    'auto' or an int) fails once per type; those reasons are joined with 'or'. A nested
    key is named with its parent (`early_stop.patience`)."""
    reasons: dict[str, list[str]] = {}
    for e in err.errors():
        loc = list(e["loc"])
        if len(loc) == 2 and isinstance(loc[1], str) and loc[0] not in NESTED_FIELDS:
            loc = loc[:1]  # a union branch tag, not a field
        field = ".".join(str(p) for p in loc) or "config"
        msg = e["msg"].removeprefix("Value error, ")
        named, _, rest = msg.partition(": ")
        if not loc and rest and named in TrainConfig.model_fields:  # "beta: ..." names it
            field, msg = named, rest
        elif len(loc) == 1 and loc[0] in NESTED_FIELDS and rest and named.isidentifier():
            field, msg = f"{loc[0]}.{named}", rest  # a nested model's own check names its key
        if e["type"] == "extra_forbidden":
            msg = "unknown key (misspelt?)"
        reasons.setdefault(field, []).append(msg)
    return "; ".join(f"{field}: {' or '.join(msgs)}" for field, msgs in reasons.items())


def error_text(err: BaseException) -> str:
    """An error as a user reads it: a ValidationError (of any model) as 'field: reason;
    ...' (`format_errors`), anything else as it says itself."""
    return format_errors(err) if isinstance(err, ValidationError) else str(err)


def make_config(data: dict[str, Any]) -> TrainConfig:
    try:
        return TrainConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(format_errors(err)) from None


PLAIN_DEPTH = 16  # nesting a config's free-form mapping may have


def plain_data(value: Any, where: str, depth: int = 0) -> None:
    """Raise ValueError naming the place unless `value` is JSON-like data: None, a bool, an
    int within 64 bits, a finite float, a string that is valid UTF-8 (no lone surrogate),
    or lists and string-keyed mappings of those, at most PLAIN_DEPTH deep."""
    if depth > PLAIN_DEPTH:
        raise ValueError(f"{where}: nested deeper than {PLAIN_DEPTH} levels")
    if value is None or isinstance(value, bool):
        return
    if isinstance(value, int):
        if not -(2**63) <= value < 2**64:
            raise ValueError(f"{where}: {value} does not fit in 64 bits")
    elif isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{where}: {value} is not a finite number")
    elif isinstance(value, str):
        try:
            value.encode("utf-8")
        except UnicodeEncodeError:
            raise ValueError(
                f"{where}: a string that is not valid UTF-8 (a lone surrogate)"
            ) from None
    elif isinstance(value, list):
        for i, item in enumerate(value):
            plain_data(item, f"{where}[{i}]", depth + 1)
    elif isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                raise ValueError(f"{where}: key {key!r} is not a string")
            plain_data(key, f"{where} key", depth + 1)
            plain_data(item, f"{where}.{key}", depth + 1)
    else:
        raise ValueError(f"{where}: a {type(value).__name__} is not plain data (JSON's kinds)")


def read_yaml_file(path: str | Path, what: str) -> Any:
    """A YAML or JSON file's data as written (YAML is a superset), not yet validated. A
    file that cannot be read, is not UTF-8 or not YAML is a ConfigError naming it; `what`
    says what it should have been (a folder given for it)."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise ConfigError(f"{path}: not UTF-8 text ({err.reason} at byte {err.start})") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: a folder, not {what}") from None
    except OSError as err:
        raise ConfigError(f"{path}: cannot be read ({err.strerror or err})") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as err:
        where = str(err).replace('"<unicode string>"', str(path))
        raise ConfigError(f"{path}: not valid YAML/JSON: {where}") from None


def read_config_file(path: str | Path) -> dict[str, Any]:
    """A config file's mapping as written (`read_yaml_file`), not yet validated."""
    data = read_yaml_file(path, "a config file")
    if data is None or data == {}:  # (empty, comments only, `{}`: another file was meant)
        raise ConfigError(f"{path}: empty: a config file holds at least one key")
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config is a mapping of keys to values")
    return data


def load_config(path: str | Path, overrides: dict[str, Any] | None = None) -> TrainConfig:
    """Read a YAML or JSON config file and apply overrides."""
    data = read_config_file(path)
    data.update(overrides or {})
    return make_config(data)
