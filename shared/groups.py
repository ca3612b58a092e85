"""Which runs may share a run group, as one rule for every place that forms one.

A group shares its task's steps and one update of all its runs' networks, so its
runs may differ only in the fields a run chooses for itself (`PER_RUN_FIELDS`). The
one-process group (cli/trainer.py), the API's scheduler, `shared.net.control` and
the learner service all ask these functions.
"""

from __future__ import annotations

import json
from collections.abc import Sequence

from shared.config import TrainConfig

#: Config fields that may differ between the runs of a group; every other field is
#: shared (task and its options, algorithm and network, update settings, episodes,
#: evaluation, precision and threads).
PER_RUN_FIELDS = frozenset(
    {
        "seed",
        "explore",
        "beta",
        "beta_schedule",
        "early_stop",
        "k",
        "hash",
        "bonus_at",
        "key",
        "hash_round",
        "count_sketch",
        "reward",
        "noise_sigma",
        "time_limit_terminal",
        "warmup",
        "same_init",
        "buffer_size",
        "profile",
        "learner_lanes",
        "learner_impl",
    }
)


def group_key(cfg: TrainConfig) -> str:
    """What runs of one group must share, as one comparable string."""
    shared = {k: v for k, v in cfg.model_dump(mode="json").items() if k not in PER_RUN_FIELDS}
    return json.dumps(shared, sort_keys=True)


def check_group(cfgs: Sequence[TrainConfig]) -> None:
    """Refuse runs that cannot share a group, naming the first field that differs, and
    runs asking for the reference learner (a group updates with the batched one)."""
    if not cfgs:
        raise ValueError("a group needs at least one run")
    for r, cfg in enumerate(cfgs):
        if cfg.learner_impl == "reference":
            raise ValueError(
                f"run {r}: learner_impl reference: a run group updates with the batched "
                "learner; run it alone with macb train"
            )
    first = json.loads(group_key(cfgs[0]))
    for r, cfg in enumerate(cfgs[1:], 1):
        other = json.loads(group_key(cfg))
        field = next((k for k in sorted(first | other) if first.get(k) != other.get(k)), None)
        if field is not None:
            raise ValueError(
                f"runs 0 and {r} cannot share a group: they differ in {field} "
                f"({getattr(cfgs[0], field)!r} != {getattr(cfg, field)!r})"
            )


def group_error(cfgs: Sequence[TrainConfig], actors: int) -> str | None:
    """Why these runs cannot be served as one group by the cluster's services, or None.
    There a group runs the thesis's loop (`interleave: lockstep`) with one actor
    stepping every run's world."""
    try:
        check_group(cfgs)
    except ValueError as err:
        return str(err)
    for r, cfg in enumerate(cfgs):
        if cfg.interleave != "lockstep":
            return f"run {r}: interleave {cfg.interleave}: a group in the cluster runs lockstep"
        if cfg.bonus_at == "collection":
            return f"run {r}: bonus_at collection: the cluster prices bonuses when it samples"
    if actors != 1:
        return f"actors: a group in the cluster has one actor (it steps every world), not {actors}"
    return None


def form_groups(cfgs: Sequence[TrainConfig], max_runs: int | None = None) -> list[list[int]]:
    """Indices of `cfgs` in groups of runs that can share one (in order of first
    appearance), each at most `max_runs` long; a run asking for the reference learner
    is a group of one (`check_group` refuses it beside others)."""
    by_key: dict[str, list[int]] = {}
    for i, cfg in enumerate(cfgs):
        # (the reference learner is one run's: such a run trains alone, as `macb train`)
        alone = f"reference run {i}" if cfg.learner_impl == "reference" else ""
        by_key.setdefault(alone or group_key(cfg), []).append(i)
    groups = []
    for members in by_key.values():
        step = max_runs or len(members)
        groups += [members[i : i + step] for i in range(0, len(members), step)]
    return groups
