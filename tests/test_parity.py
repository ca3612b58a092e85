"""bf16's learning parity: the criterion (pure logic) and the benchmark's quick run (slow).

The criterion is benchmarks/parity.py's paired TOST; these tests pin what it says for
cases whose answer is known, and that its p-values are scipy's own paired t-tests."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from shared.core.learners.precision import native_bf16

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))  # the criterion lives beside its benchmark
from parity import curve_auc, paired_equivalence  # noqa: E402


def test_curve_auc_is_the_mean_over_points_and_refuses_no_rows():
    rows = [{"success_rate": 0.0}, {"success_rate": 0.5}, {"success_rate": 1.0}]
    assert curve_auc(rows) == pytest.approx(0.5)
    with pytest.raises(ValueError, match="no evaluation rows"):
        curve_auc([])


def test_close_pairs_are_equivalent_far_ones_different_noisy_ones_inconclusive():
    rng = np.random.default_rng(0)
    a = rng.uniform(0.3, 0.9, size=10)
    close = paired_equivalence(a, a + rng.normal(0, 0.01, 10), margin=0.1)
    assert close.verdict == "equivalent" and close.p_tost < 0.05
    far = paired_equivalence(a, a - 0.5 + rng.normal(0, 0.01, 10), margin=0.1)
    assert far.verdict == "different" and far.ci_high < -0.1
    noisy = paired_equivalence(a[:3], a[:3] + np.array([0.3, -0.3, 0.05]), margin=0.1)
    assert noisy.verdict == "inconclusive"  # no difference found, and no parity shown


def test_p_values_are_scipys_paired_t_tests():
    rng = np.random.default_rng(1)
    a, b = rng.normal(0.5, 0.1, 7), rng.normal(0.52, 0.1, 7)
    res = paired_equivalence(a, b, margin=0.15)
    assert res.p_difference == pytest.approx(stats.ttest_rel(b, a).pvalue)
    lower = stats.ttest_1samp(b - a, -0.15, alternative="greater").pvalue
    upper = stats.ttest_1samp(b - a, 0.15, alternative="less").pvalue
    assert res.p_tost == pytest.approx(max(lower, upper))
    # the interval is inside the band exactly when both one-sided tests reject
    assert (res.verdict == "equivalent") == (res.p_tost < 0.05)


def test_identical_runs_are_equivalent_and_bad_input_is_refused():
    same = paired_equivalence([0.2, 0.4, 0.6], [0.2, 0.4, 0.6], margin=0.1)
    assert same.verdict == "equivalent" and same.mean_diff == 0 and same.p_difference == 1
    with pytest.raises(ValueError, match="pairs needed"):
        paired_equivalence([0.1, 0.2], [0.1], margin=0.1)
    with pytest.raises(ValueError, match="at least 2 seeds"):
        paired_equivalence([0.1], [0.1], margin=0.1)
    with pytest.raises(ValueError, match="margin must be > 0"):
        paired_equivalence([0.1, 0.2], [0.1, 0.2], margin=0)


@pytest.mark.slow
@pytest.mark.skipif(not native_bf16(), reason="this CPU has no native bf16: bf16 would run fp32")
def test_bf16_learns_sparse_simple_like_fp32(tmp_path: Path) -> None:
    """bench_parity --quick: DDPG + Dis-MACB on sparse simple, 3 seeds x 400 episodes in
    each precision. Three seeds cannot show equivalence (the benchmark's 8 seeds are
    for that, docs/performance.md); what they can show is that bf16 learns where fp32
    does: a bf16 whose updates were wrong stays near 0 success while fp32 reaches it."""
    out = tmp_path / "parity.json"
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_parity.py"), "--quick"]
    proc = subprocess.run(
        [*argv, "--out", str(out)], capture_output=True, text=True, timeout=900, check=False
    )
    assert proc.returncode == 0, proc.stderr
    assert "| simple | bf16 | success_auc | 3 |" in proc.stdout
    (res,) = json.loads(out.read_text())["results"]
    success = res["tests"][0]
    assert success["metric"] == "success_auc" and success["verdict"] != "different", success
    assert success["mean_a"] > 0.15, "fp32 did not learn: the check would say nothing"
    assert success["mean_b"] > 0.5 * success["mean_a"], success
