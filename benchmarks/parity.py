"""Do two precisions learn alike? The statistical criterion of bf16's learning parity.

One run's learning is summed up by the area under its evaluation curve: the mean of a
metric (success rate, evaluation return) over all its evaluation points, which weighs
early and late learning alike and needs no threshold. fp32 and bf16 runs are paired by
seed (same initial weights, noise and environment draws until their roundings part
them), so the per-seed difference d = AUC(bf16) - AUC(fp32) carries what precision did.

The criterion is an equivalence test (two one-sided t-tests, TOST, on the paired d):
bf16 learns like fp32 when the (1 - 2 alpha) confidence interval of the mean of d lies
inside (-margin, +margin). A plain difference test cannot show parity (too few seeds
to find a difference proves nothing), so its p-value is reported beside, not used.
With few seeds the interval is wide and the verdict is `inconclusive`, which says the
evidence is missing, not that bf16 differs; `different` needs the interval wholly
outside the margin's band.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy import stats


def curve_auc(rows: Iterable[Mapping[str, Any]], key: str = "success_rate") -> float:
    """The mean of `key` over a run's evaluation rows (its curve's area per point)."""
    values = [float(r[key]) for r in rows]
    if not values:
        raise ValueError(f"no evaluation rows to take the mean of {key!r} over")
    return float(np.mean(values))


@dataclass(frozen=True)
class Parity:
    """The paired comparison of one metric: b (bf16) against a (fp32)."""

    metric: str
    n: int
    mean_a: float
    mean_b: float
    mean_diff: float  # mean of b - a over seeds
    ci_low: float  # the (1 - 2 alpha) interval of mean_diff
    ci_high: float
    margin: float
    alpha: float
    p_tost: float  # the larger one-sided p: < alpha iff the interval is inside the band
    p_difference: float  # two-sided paired t-test, reported only
    verdict: str  # "equivalent", "inconclusive" or "different"

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def paired_equivalence(
    a: Sequence[float], b: Sequence[float], margin: float, alpha: float = 0.05, metric: str = ""
) -> Parity:
    """TOST on the paired differences b - a with equivalence band (-margin, margin)."""
    if len(a) != len(b):
        raise ValueError(f"{len(a)} fp32 runs against {len(b)} bf16 runs: pairs needed")
    if len(a) < 2:
        raise ValueError("at least 2 seeds are needed for an interval")
    if not margin > 0:
        raise ValueError(f"margin must be > 0, got {margin}")
    d = np.asarray(b, dtype=float) - np.asarray(a, dtype=float)
    n = len(d)
    mean = float(d.mean())
    se = float(d.std(ddof=1)) / math.sqrt(n)
    t_crit = float(stats.t.ppf(1 - alpha, n - 1))
    low, high = mean - t_crit * se, mean + t_crit * se
    if se == 0.0:  # identical differences: the interval is the point itself
        p_low = p_high = 0.0 if -margin < mean < margin else 1.0
        p_diff = 1.0 if mean == 0.0 else 0.0
    else:
        p_low = float(stats.t.sf((mean + margin) / se, n - 1))  # H0: mean <= -margin
        p_high = float(stats.t.cdf((mean - margin) / se, n - 1))  # H0: mean >= +margin
        p_diff = float(2 * stats.t.sf(abs(mean) / se, n - 1))
    if -margin < low and high < margin:
        verdict = "equivalent"
    elif high <= -margin or low >= margin:
        verdict = "different"
    else:
        verdict = "inconclusive"
    return Parity(
        metric=metric,
        n=n,
        mean_a=float(np.mean(a)),
        mean_b=float(np.mean(b)),
        mean_diff=mean,
        ci_low=low,
        ci_high=high,
        margin=margin,
        alpha=alpha,
        p_tost=max(p_low, p_high),
        p_difference=p_diff,
        verdict=verdict,
    )
