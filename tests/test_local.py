"""Run groups where users get them: `macb train --seeds`, `macb run --local` and
`macb reproduce --local` (real processes, real files): each run's folder holds what
`macb train` writes for it alone, a killed command continues to the same rows, a
finished one re-runs nothing, and `--report-only` rebuilds a figure's page from the
stored runs, its numbers those of its CSV."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest

from cli.results import read_points
from tests.harness import macb, spawn

TIMING = ("steps_per_sec", "train_steps_per_sec", "wall_s")
SMALL = ["--hidden", "16,16", "--learning-starts", "20", "--batch-size", "8",
         "--learner-lanes", "1"]  # fmt: skip


def rows(folder: Path) -> list[dict]:
    lines = (folder / "metrics.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(x).items() if k not in TIMING} for x in lines]


def test_train_seeds_runs_a_group_whose_runs_equal_their_lone_runs(tmp_path):
    base = ["train", "--task", "simple", "--algo", "ddpg", "--episodes", "4", *SMALL, "--quiet"]
    got = macb(*base, "--seeds", "3", "5", "--out", str(tmp_path / "g"))
    assert got.returncode == 0, got.stderr
    for seed in (3, 5):
        alone = macb(*base, "--seed", str(seed), "--out", str(tmp_path / f"a{seed}"))
        assert alone.returncode == 0, alone.stderr
        folder = tmp_path / "g" / f"seed-{seed}"
        assert rows(folder) == rows(tmp_path / f"a{seed}")
        for name in ("metrics.csv", "config.json", "provenance.json", "checkpoint.pt"):
            assert (folder / name).exists(), name
    again = macb(*base, "--seeds", "3", "5", "--out", str(tmp_path / "g"))
    assert "2 of 2 runs complete, skipped" in again.stderr
    # Another config over the same folders: refused, naming the field; nothing touched.
    before = (tmp_path / "g" / "seed-3" / "metrics.jsonl").read_text()
    other = macb(*base[:-1], "--episodes", "6", "--quiet", "--seeds", "3", "5",
                 "--out", str(tmp_path / "g"))  # fmt: skip
    assert other.returncode == 2 and "holds a run of another config (episodes" in other.stderr
    assert (tmp_path / "g" / "seed-3" / "metrics.jsonl").read_text() == before
    bad = macb(*base, "--seeds", "3", "3", "--out", str(tmp_path / "bad"))
    assert bad.returncode == 2 and "given twice" in bad.stderr


def test_a_killed_local_run_continues_to_the_same_rows(tmp_path):
    config = tmp_path / "exp.yaml"
    config.write_text(
        "task: speaker_listener\nalgo: cen-maddpg\nexplore: cen-macb\nk: 16\nepisodes: 40\n"
        "hidden: [32, 32]\nbatch_size: 16\nlearning_starts: 40\nlearner_lanes: 1\n"
        "arms:\n  - {name: counted, explore: cen-macb}\n  - {name: constant, explore: constant}\n"
    )
    args = ["run", str(config), "--local", "--seeds", "0", "1", "--jobs", "1", "--quiet"]
    straight = macb(*args, "--out", str(tmp_path / "straight"))
    assert straight.returncode == 0, straight.stderr
    names = sorted(p.name for p in (tmp_path / "straight").iterdir() if p.is_dir())
    assert names == ["constant-s0", "constant-s1", "counted-s0", "counted-s1"]
    assert (tmp_path / "straight" / "plot.png").exists()

    out = tmp_path / "killed"
    proc = spawn(*args, "--out", str(out))
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # past the first cut (every run cuts its 1st point)
            cuts = list(out.glob("*/cuts/cut-*.pt"))
            done = [p for p in out.glob("*/metrics.jsonl") if len(p.read_text().splitlines()) > 5]
            if len(cuts) >= 4 and done:
                break
            time.sleep(0.1)
        assert proc.poll() is None, "the run ended before it could be killed"
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert len(rows(out / "counted-s0")) < 40, "killed too late to test anything"
    resumed = macb(*args, "--out", str(out))
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming from cut-" in resumed.stderr
    for name in names:
        assert rows(out / name) == rows(tmp_path / "straight" / name), name


def test_reproduce_local_and_report_only(tmp_path):
    out = tmp_path / "fig3"
    got = macb("reproduce", "fig3", "--local", "--episodes", "6", "--seeds", "0",
               "--jobs", "2", "--quiet", "--out", str(out))  # fmt: skip
    assert got.returncode == 0, got.stderr
    assert "11 completed" in got.stderr
    md = (out / "fig3.md").read_text()
    record = json.loads((out / "fig3-runs.json").read_text())
    assert len(record["runs"]) == 11 and all(r["provenance"]["machine"] for r in record["runs"])
    assert "- Wall time: " in md and "macb reproduce fig3 --local --episodes 6" in md
    table = read_points(out / "fig3.csv.gz")
    # every stored row is in the CSV, with the same numbers
    for run in (out / "runs").iterdir():
        mine = [r for r in table if r["run"] == run.name]
        stored = rows(run)
        assert len(mine) == len(stored) == 6
        assert [float(r["success_rate"]) for r in mine] == [r["success_rate"] for r in stored]
    (out / "fig3.md").unlink()
    again = macb("reproduce", "fig3", "--report-only", "--episodes", "6", "--seeds", "0",
                 "--out", str(out))  # fmt: skip
    assert again.returncode == 0, again.stderr
    rebuilt = (out / "fig3.md").read_text()
    drop = lambda text: [  # noqa: E731  (the command and the build's minute differ)
        x for x in text.splitlines() if "Reproduced with" not in x and "page built" not in x
    ]
    assert drop(rebuilt) == drop(md)
    page = tmp_path / "page"  # a page written elsewhere from the stored runs
    moved = macb("reproduce", "fig3", "--report-only", "--episodes", "6", "--seeds", "0",
                 "--runs", str(out / "runs"), "--out", str(page))  # fmt: skip
    assert moved.returncode == 0, moved.stderr
    assert drop((page / "fig3.md").read_text()) == drop(md) and not (page / "runs").exists()
    none = macb("reproduce", "fig3", "--report-only", "--out", str(tmp_path / "empty"))
    assert none.returncode == 2 and "no runs stored" in none.stderr
    a_file = tmp_path / "a-file"  # a page's --out that is a file: refused, no traceback
    a_file.write_text("")
    filed = macb("reproduce", "fig3", "--report-only", "--episodes", "6", "--seeds", "0",
                 "--runs", str(out / "runs"), "--out", str(a_file))  # fmt: skip
    assert filed.returncode == 2 and "Traceback" not in filed.stderr, filed.stderr
    assert f"--out {a_file}: cannot write the page there (a file, not a folder)" in filed.stderr


def test_reproduce_arms_runs_only_the_arms_named_and_refuses_a_pattern_of_none(tmp_path):
    out = tmp_path / "fig3"
    got = macb("reproduce", "fig3", "--local", "--episodes", "3", "--seeds", "0", "--quiet",
               "--arms", "beta=0.8", "CONSTANT beta=0.8*", "--out", str(out))  # fmt: skip
    assert got.returncode == 0, got.stderr
    assert "2 completed" in got.stderr
    assert sorted(p.name for p in (out / "runs").iterdir()) == [
        "beta_0.8-s0",
        "constant_beta_0.8_control-s0",
    ]
    md = (out / "fig3.md").read_text()
    assert '| beta=0.0 | explore="none", beta=0.0 | 0 |' in md  # listed, no runs
    bad = macb("reproduce", "fig3", "--local", "--arms", "sparse*", "--out", str(tmp_path))
    assert bad.returncode == 2
    assert "--arms 'sparse*': no arm of fig3 matches (beta=0.0; beta=0.2;" in bad.stderr


@pytest.mark.slow  # a whole cluster or campaign run: ~35-55 s alone on 2 cores
def test_runs_of_another_config_are_neither_trained_on_nor_shown_as_the_figure_s(tmp_path):
    """A page, a --local campaign or a view asked for runs of another length than its
    folders hold refuses, naming the folder and the field, and writes nothing: the
    folders' rows would otherwise stand on the page as runs of the config asked. So
    does a page or --status given a folder holding none of the runs (OUT for OUT/runs):
    an empty page would replace the one there."""
    out = tmp_path / "fig3"
    flags = ["--seeds", "0", "--arms", "beta=0.8", "--threads", "2", "--out", str(out)]
    first = macb("reproduce", "fig3", "--local", "--episodes", "3", "--quiet", *flags)
    assert first.returncode == 0, first.stderr
    pages = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    rows_before = (out / "runs" / "beta_0.8-s0" / "metrics.jsonl").read_bytes()
    why = f"{out / 'runs' / 'beta_0.8-s0'}: holds a run of another config (episodes: 3 in "
    wrong_folder = ["--episodes", "3", "--runs", str(out)]
    for mode, more in [("--report-only", ["--episodes", "4"]), ("--local", ["--episodes", "4"]),
                       ("--report-only", wrong_folder), ("--status", wrong_folder),
                       ("--status", ["--episodes", "4"]),
                       ("--report-only", ["--group-runs", "beta_0.8-s0"])]:  # fmt: skip
        other = macb("reproduce", "fig3", mode, *more, "--quiet", *flags)
        assert other.returncode == 2, (mode, other.stderr)
        if "--group-runs" in more:
            assert "--group-runs trains with --local (not with --report-only" in other.stderr
        elif "--runs" in more:
            assert f"none of the 1 run(s) selected has a folder in {out}" in other.stderr
        else:
            assert why in other.stderr and "4 in the run" in other.stderr, other.stderr
        assert "wrote" not in other.stderr and "Traceback" not in other.stderr, other.stderr
        assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == pages
        assert (out / "runs" / "beta_0.8-s0" / "metrics.jsonl").read_bytes() == rows_before
    # Other runs' folders and none of these (another --seeds): a mistake, refused.
    seeds1 = ["--seeds", "1", *flags[2:]]
    elsewhere = f"none of the 1 run(s) selected has a folder in {out / 'runs'}, which holds "
    for argv in (["reproduce", "fig3", "--status", "--episodes", "3", *seeds1],
                 ["view", str(out), "--figure", "fig3", "--episodes", "3", "--port", "0",
                  *seeds1[:-2]]):  # fmt: skip
        got = macb(*argv, timeout=60)
        assert got.returncode == 2, got.stdout + got.stderr
        assert elsewhere + "other runs (beta_0.8-s0)" in got.stderr, got.stderr
    # The figure's other arms (that run later) are not other runs: not started, exit 0.
    later_arm = ["--seeds", "0", "--arms", "beta=0.0", "--threads", "2", "--out", str(out)]
    got = macb("reproduce", "fig3", "--status", "--episodes", "3", *later_arm, timeout=60)
    assert got.returncode == 0 and "not started" in got.stdout, got.stdout + got.stderr
    # A runs folder none of whose runs has started (queued on Slurm, arms that run later)
    # is a campaign not started, not a mistake: --status says so.
    (tmp_path / "later").mkdir()
    later = macb("reproduce", "fig3", "--status", "--episodes", "3", "--quiet", *flags[:-1],
                 str(tmp_path / "o"), "--runs", str(tmp_path / "later"))  # fmt: skip
    assert later.returncode == 0 and "not started" in later.stdout, later.stdout + later.stderr
    view = ["view", str(out), "--figure", "fig3", "--seeds", "0", "--arms", "beta=0.8",
            "--port", "0"]  # fmt: skip
    other = macb(*view, "--threads", "2", "--episodes", "4", timeout=60)
    assert other.returncode == 2 and why in other.stderr, other.stderr
    threads = macb(*view, "--episodes", "3", timeout=60)  # the view has --threads for this
    assert threads.returncode == 2, threads.stderr
    assert "(threads: 2 in the folder, 1 in the run)" in threads.stderr, threads.stderr
    same = macb("reproduce", "fig3", "--report-only", "--episodes", "3", *flags)
    assert same.returncode == 0, same.stderr
    # The page names the command that trains these runs: their flags and their folder.
    rebuild = "macb reproduce fig3 --local --profile mpe2 --seeds 0 --episodes 3 --threads 2 "
    assert rebuild in (out / "fig3.md").read_text()
    moved = macb("reproduce", "fig3", "--report-only", "--episodes", "3", *flags[:-1],
                 str(tmp_path / "page"), "--runs", str(out / "runs"))  # fmt: skip
    assert moved.returncode == 0, moved.stderr
    assert f"--runs {out / 'runs'} --arms beta=0.8`" in (tmp_path / "page" / "fig3.md").read_text()


@pytest.mark.parametrize("flag", ["--jobs", "--group-size", "--threads"])
def test_reproduce_refuses_bad_counts(flag, tmp_path):
    got = macb("reproduce", "fig3", "--local", flag, "0", "--out", str(tmp_path))
    assert got.returncode == 2 and flag in got.stderr


def test_a_row_being_written_is_not_read_yet(tmp_path):
    """A page built while a campaign runs reads each run's rows as they stand: a last
    line without its newline (a row half written) is left for the next read."""
    from cli.local import run_rows

    (tmp_path / "metrics.jsonl").write_text('{"episode": 10}\n{"episode": 20}\n{"epis')
    assert [r["episode"] for r in run_rows(tmp_path)] == [10, 20]
    (tmp_path / "metrics.jsonl").write_text('{"episode": 10}\n{"episode": 20}\n')
    assert [r["episode"] for r in run_rows(tmp_path)] == [10, 20]


def test_jobs_default_to_one_group_per_cpu_or_per_gpu(monkeypatch):
    """Without --jobs: one group per CPU for runs on the CPU; on a GPU one per GPU the
    runs' device names (every one of a bare `cuda`, one of `cuda:N`)."""
    import cli.local as local
    import shared.core.learners.precision as precision
    from shared.config import make_config

    def four_gpus(device: str) -> int:
        return 0 if device == "cpu" else 1 if ":" in device else 4

    monkeypatch.setattr(precision, "device_count", four_gpus)
    monkeypatch.setattr(os, "cpu_count", lambda: 16)
    base = {"task": "simple", "algo": "ddpg"}
    cpu = make_config(base)
    cuda, cuda1 = (make_config({**base, "device": d}) for d in ("cuda", "cuda:1"))
    assert local.default_jobs([cpu, cpu]) == 16
    assert local.default_jobs([cuda, cuda]) == 4
    assert local.default_jobs([cuda1]) == 1
    # The processes of a bare `cuda` take the GPUs in turn; a numbered one is the run's own.
    assert local._spread_devices([cuda, cuda], 4) == "cuda"
    assert local._spread_devices([cuda1, cuda1], 4) is None
    assert local._spread_devices([cpu], 4) is None and local._spread_devices([cuda], 1) is None
    import torch

    taken: list[int] = []
    monkeypatch.setattr(torch.cuda, "set_device", taken.append)
    for slot in (2, 5):
        local._take_device("cuda", slot)
    assert taken == [2, 1]  # a process's slot names its GPU, in turn over the four
