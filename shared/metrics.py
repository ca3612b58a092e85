"""The fields of a metric row, in one place: the trainer's CSV, the services' rows and
the API's store and CSV all use these names, in this order, and the early-stopping rule
read on them. (No numpy or torch here: the API imports it.)"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from shared.config import EarlyStop, TrainConfig

TRAIN_FIELDS = (
    "episode",
    "env_steps",
    "success_rate",
    "eval_return",
    "collisions_cum",
    "count1_pct",
    "table_size",
    "counted_transitions",
    "bonus_mean",
    "bonus_std",
    "sampled_count1_pct",
    "steps_per_sec",
    "train_steps_per_sec",
    "updates",
    "wall_s",
)
# What a distributed run adds to each row.
SERVICE_FIELDS = ("replay_ratio", "policy_lag", "policy_version")
ALL_FIELDS = TRAIN_FIELDS + SERVICE_FIELDS
# What a run's rows add when it sets the option (beyond the thesis): `beta`, the beta in
# force at the point's last transition (`beta_schedule`), and `stop_reason`, set on the
# point its `early_stop` rule ends it at. A run without them writes the rows it always did.
OPTION_FIELDS = ("beta", "stop_reason")
# What a curve may draw: every number a row may hold (`episode`, its x, too).
CURVE_FIELDS = (*ALL_FIELDS, "beta")


def curve_field_error(name: str) -> str | None:
    """Why `name` is no metric a curve may draw (None if it is one)."""
    if name in CURVE_FIELDS:
        return None
    return f"unknown metric {name[:64]!r} (one of: {', '.join(CURVE_FIELDS)})"


def run_fields(cfg: TrainConfig, base: tuple[str, ...] = TRAIN_FIELDS) -> tuple[str, ...]:
    """The columns of `cfg`'s rows: `base` and the options it sets."""
    extra = (("beta",) if cfg.beta_schedule is not None else ()) + (
        ("stop_reason",) if cfg.early_stop is not None else ()
    )
    return base + extra


def smoothed(values: Sequence[float], window: int) -> list[float]:
    """The trailing mean of the last `window` values at each point (fewer at the start):
    what the rule reads, known at each point without the points after it."""
    out, total = [], 0.0
    for i, v in enumerate(values):
        total += v
        if i >= window:
            total -= values[i - window]
        out.append(total / min(i + 1, window))
    return out


# Smoothed means closer than this are one value to the rules: a running float mean of
# 0.7, 1.0, 1.0 is 0.8999999999999999, and 0.0, 0.2 then 0.2, 0.0 read as an improvement.
# Far above the running sum's rounding, far below any two success rates that differ.
SAME_WITHIN = 1e-9


def early_stop_reason(rule: EarlyStop | None, rows: Sequence[dict]) -> str | None:
    """Why the run ends at its last row by `rule` (config `early_stop`), or None: a pure
    function of the rows so far, so a resumed run and every place that reads rows (the
    trainer, a group's members, the reports) decide alike."""
    if rule is None or not rows:
        return None
    sm = smoothed([float(r["success_rate"]) for r in rows], rule.smooth)
    what = "success rate" if rule.smooth == 1 else f"success rate (mean of {rule.smooth} points)"
    if rule.rule == "success_at_least":
        assert rule.threshold is not None
        tail = sm[-rule.patience :]
        if len(tail) == rule.patience and all(v >= rule.threshold - SAME_WITHIN for v in tail):
            return (
                f"early_stop success_at_least at episode {rows[-1]['episode']}: {what} >= "
                f"{rule.threshold:g} at {rule.patience} point(s) in a row"
            )
        return None
    best, at = sm[0], 0
    for i, v in enumerate(sm[1:], 1):
        if v > best + rule.min_delta + SAME_WITHIN:
            best, at = v, i
    if len(sm) - 1 - at >= rule.patience:
        return (
            f"early_stop no_improvement at episode {rows[-1]['episode']}: {what} not "
            f"above {best:.3g} (episode {rows[at]['episode']}) for {rule.patience} point(s)"
        )
    return None
