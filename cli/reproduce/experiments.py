"""A figure's arms as configs and as an experiment: each arm's file read under a
profile, the body POST /experiments takes (or `--local` expands), its name, the arms
`--arms` keeps, and each counting arm's constant control.
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path
from typing import Any

from cli.reproduce.defs import PROFILES, ArmDef, FigureDef
from shared.config import COUNTING_EXPLORE, TrainConfig, read_config_file

# Keys only counting reads: a control (no counting) matches its MACB arm on all others.
COUNTING_KEYS = ("explore", "k", "hash", "key", "hash_round")
# Keys of a config file that are the experiment's, not one run's.
EXPERIMENT_KEYS = ("seeds",)


def configs_file(name: str) -> Path:
    """A figure's arm file in the shipped configs/ (`shared.settings.shipped_configs`);
    a missing one is refused naming the folder and how to give another."""
    from shared.settings import shipped_configs

    path = shipped_configs() / name
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: no such config file (the figures read the shipped configs/ folder: "
            "run from a checkout, or set MACB_CONFIGS_DIR to a copy of it)"
        )
    return path


def arm_file(arm: ArmDef) -> dict[str, Any]:
    """The arm's config file as written, without the experiment's keys (seeds); an arm
    read from its runs gives its runs' config."""
    if arm.config is not None:
        return {k: v for k, v in arm.config.items() if k not in EXPERIMENT_KEYS}
    data = read_config_file(configs_file(arm.file))
    return {k: v for k, v in data.items() if k not in EXPERIMENT_KEYS}


def arm_configs(fig: FigureDef) -> dict[str, dict[str, Any]]:
    """Every arm's config keys as its file gives them, by arm name."""
    return {a.name: arm_file(a) for a in fig.arms}


def file_seeds(fig: FigureDef) -> list[int]:
    """The seeds the figure's files list (all the same; tests check it)."""
    seeds = {json.dumps(read_config_file(configs_file(a.file)).get("seeds")) for a in fig.arms}
    if len(seeds) != 1 or seeds == {"null"}:
        raise ValueError(f"{fig.name}: its config files list different seeds: {seeds}")
    return json.loads(seeds.pop())


def split_base(configs: dict[str, dict[str, Any]]) -> tuple[dict[str, Any], dict[str, dict]]:
    """(keys every arm sets to the same value, each arm's other keys)."""
    files = list(configs.values())
    base = {k: v for k, v in files[0].items() if all(k in f and f[k] == v for f in files[1:])}
    return base, {n: {k: v for k, v in c.items() if k not in base} for n, c in configs.items()}


def profile_arm_configs(fig: FigureDef, profile: str) -> dict[str, dict[str, Any]]:
    """Every arm's config keys under a profile: its file's, and under `profile: thesis`
    the figure's `thesis_method` over each counting arm."""
    configs = arm_configs(fig)
    if profile == "thesis" and fig.thesis_method:
        method = dict(fig.thesis_method)
        configs = {n: {**c, **method} if counts(c) else c for n, c in configs.items()}
    return configs


def full_config(fig: FigureDef, arm: str, profile: str, **over: Any) -> TrainConfig:
    """An arm's whole run config under a profile (what its runs get, but the seed)."""
    configs = profile_arm_configs(fig, profile)
    return TrainConfig.model_validate({**configs[arm], "profile": profile, **over})


def experiment_body(
    fig: FigureDef,
    profile: str,
    seeds: list[int],
    episodes: int | None,
    precision: str | None = None,
) -> dict[str, Any]:
    """The POST /experiments body of a figure: the shared keys as the base, one arm per
    config file setting the rest; `episodes` (if given) cuts every run short and
    `precision` (if given) sets every run's learner precision."""
    if profile not in PROFILES:
        raise ValueError(f"unknown profile {profile!r} (profiles: {', '.join(PROFILES)})")
    base, arms = split_base(profile_arm_configs(fig, profile))
    base = {**base, "profile": profile}
    for key, value in (("episodes", episodes), ("precision", precision)):
        if value is not None:
            base[key] = value
            arms = {n: {k: v for k, v in a.items() if k != key} for n, a in arms.items()}
    return {
        **base,
        "seeds": list(seeds),
        "arms": [{"name": n, **a} for n, a in arms.items()],
    }


def select_arms(fig: FigureDef, body: dict[str, Any], patterns: list[str]) -> dict[str, Any]:
    """The body with only the arms whose name matches one of `patterns` (shell-style,
    any case: "Sparse*"), in the figure's order; ValueError naming a pattern that
    matches no arm, and the arms there are."""
    import fnmatch

    names = [a["name"] for a in body["arms"]]
    keep: set[str] = set()
    for pattern in patterns:
        hits = [n for n in names if fnmatch.fnmatch(n.lower(), pattern.lower())]
        if not hits:
            listed = "; ".join(names)
            raise ValueError(f"--arms {pattern!r}: no arm of {fig.name} matches ({listed})")
        keep.update(hits)
    return {**body, "arms": [a for a in body["arms"] if a["name"] in keep]}


def experiment_name(fig: FigureDef, body: dict[str, Any]) -> str:
    """The experiment's name, which `macb reproduce` finds it again by: the figure, the
    profile, the length, the seeds, and a digest of the whole body, so an edited config
    file makes a new experiment instead of resuming the old one."""
    digest = hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()[:8]
    length = body.get("episodes") or "full"
    seeds = ",".join(map(str, body["seeds"]))
    ran = f" precision={body['precision']}" if body.get("precision", "fp32") != "fp32" else ""
    if body.get("device", "cpu") != "cpu":
        ran += f" device={body['device']}"
    return (
        f"reproduce {fig.name} profile={body['profile']} episodes={length} seeds={seeds}"
        f"{ran} [{digest}]"
    )


def figure_body(fig: FigureDef, args: argparse.Namespace) -> dict[str, Any]:
    """The experiment body of FIGURE under the flags (profile, seeds, episodes, arms,
    precision, threads), validated as the API would: ValueError / ValidationError."""
    from services.api.schemas import ExperimentCreate

    seeds = args.seeds or file_seeds(fig)
    body = experiment_body(fig, args.profile, seeds, args.episodes, args.precision)
    if args.arms:
        body = select_arms(fig, body, args.arms)
    if args.threads is not None:
        body["threads"] = args.threads
    if getattr(args, "device", None) not in (None, "cpu"):
        body["device"] = args.device
    if not (args.local or args.report_only or args.status):  # groups: the thesis's loop
        body["interleave"] = args.interleave
    body["name"] = experiment_name(fig, body)
    ExperimentCreate.model_validate(body)  # refused here, before any process starts
    return body


def every_arms_runs(fig: FigureDef, args: argparse.Namespace) -> set[str]:
    """The names of the figure's runs under the flags but --arms: a selection's siblings
    (arms that run later are not started, not another campaign's runs)."""
    from cli.local import expand_body

    every = figure_body(fig, argparse.Namespace(**{**vars(args), "arms": None}))
    return {r.name for r in expand_body(every)[2]}


# ---------------------------------------------------------------- controls
def counts(config: dict[str, Any]) -> bool:
    """The arm counts (Dis- or Cen-MACB): a config's keys as its file gives them, where
    a missing `explore` is the default's."""
    explore = config.get("explore", TrainConfig.model_fields["explore"].default)
    return explore in COUNTING_EXPLORE


def control_of(fig: FigureDef, arm: str) -> str | None:
    """The constant-bonus arm whose config equals this MACB arm's but for the keys only
    counting reads (same algo, beta, reward, ...); None if it has none."""
    configs = arm_configs(fig)

    def rest(c: dict[str, Any]) -> dict[str, Any]:
        full = TrainConfig.model_validate(c).model_dump(mode="json")
        return {k: v for k, v in full.items() if k not in COUNTING_KEYS}

    mine = rest(configs[arm])
    for name, c in configs.items():
        if c.get("explore") == "constant" and rest(c) == mine:
            return name
    return None
