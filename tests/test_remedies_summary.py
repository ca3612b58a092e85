"""docs/results/remedies/summary.py, the table of the remedies page: its per-run numbers
on rows whose answers are known."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
SPEC = importlib.util.spec_from_file_location(
    "remedies_summary", ROOT / "docs" / "results" / "remedies" / "summary.py"
)
assert SPEC is not None and SPEC.loader is not None
summary = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(summary)


def test_a_run_that_rises_and_falls_and_one_stopped_by_its_rule():
    rates = [0.0, 0.5, 0.9, 0.9, 0.9, 1.0, 0.6, 0.3, 0.3, 0.3, 0.3, 0.3, 0.3, 0.3]
    g = pd.DataFrame({"episode": [50 * (i + 1) for i in range(len(rates))],
                      "success_rate": rates, "stop_reason": [None] * len(rates)})  # fmt: skip
    got = summary.per_run(g)
    assert got["episodes run"] == 700
    assert got["first >= 0.9"] == 250  # the mean of 0.9, 0.9, 0.9 (episodes 150-250)
    assert got["peak"] == round((0.9 + 0.9 + 1.0) / 3, 3)
    last = sum(rates[-10:]) / 10
    assert got["last 10 points"] == round(last, 3)
    assert got["fall"] == round((0.9 + 0.9 + 1.0) / 3 - last, 3)
    assert got["stopped by its rule at"] is None
    stopped = g.head(6).assign(stop_reason=[""] * 5 + ["early_stop success_at_least"])
    assert summary.per_run(stopped)["stopped by its rule at"] == 300
    table = summary.markdown(pd.DataFrame([{"arm": "a", **got}]))
    assert table.splitlines()[0].startswith("| arm | episodes run |") and "| 700 |" in table
