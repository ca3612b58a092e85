"""Runs cut by the code before the one-trainer change resume under today's code.

tests/data/cuts-add0c53/ holds folders written by commit add0c53 (its README says how):
one `macb train` run stopped after its cut at episode 4, and a group of 2 stopped after
writing one run's row of episode 6 but before the cuts of 6. Resumed here (from a copy),
each gives the rows that the old code gave run to the end without stopping, every column
but the timing ones: what a `macb reproduce` campaign started before the change and
resumed after it relies on."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from cli.trainer import train, train_group
from shared.config import load_config

DATA = Path(__file__).parent / "data" / "cuts-add0c53"
TIMING = ("steps_per_sec", "train_steps_per_sec", "wall_s")


def strip(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMING} for r in rows]


def expected() -> dict:
    return json.loads((DATA / "expected.json").read_text())


def starts(out: Path) -> list[dict]:
    return json.loads((out / "provenance.json").read_text())["starts"]


def test_a_run_cut_by_the_old_trainer_resumes_to_its_uninterrupted_rows(tmp_path):
    out = tmp_path / "run"
    shutil.copytree(DATA / "train-cut", out)
    cfg = load_config(out / "config.json")
    rows = train(cfg, out, progress=False, resume=True, cut_every_s=0)
    want = expected()["train"]
    assert [r["episode"] for r in rows] == [2, 4, 6, 8]
    assert strip(rows) == want
    written = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert strip(written) == want
    assert [s["role"] for s in starts(out)] == ["trainer", "trainer"]


def test_a_group_cut_by_the_old_group_trainer_resumes_to_its_uninterrupted_rows(tmp_path):
    outs = [tmp_path / f"run-{r}" for r in range(2)]
    for r, out in enumerate(outs):
        shutil.copytree(DATA / "group-cut" / f"run-{r}", out)
    # run 0 had written its row of episode 6 past the cut: it is dropped and redone
    assert len((outs[0] / "metrics.jsonl").read_text().splitlines()) == 3
    cfgs = [load_config(out / "config.json") for out in outs]
    rows = train_group(cfgs, outs, progress=False, resume=True, cut_every_s=0)
    want = expected()["group"]
    for r in range(2):
        assert [row["episode"] for row in rows[r]] == [2, 4, 6, 8]
        assert strip(rows[r]) == want[r], f"run {r}"
        assert [s["role"] for s in starts(outs[r])] == ["group", "group"]


def test_one_run_of_the_old_group_resumes_alone(tmp_path):
    """Each run's cut of the old group is a one-run cut: run 1 goes on by itself (its
    learner is then the one its config builds alone, equal in fp32 with one lane)."""
    out = tmp_path / "run-1"
    shutil.copytree(DATA / "group-cut" / "run-1", out)
    rows = train(load_config(out / "config.json"), out, progress=False, resume=True)
    assert strip(rows) == expected()["group"][1]
