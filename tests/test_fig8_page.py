"""Where a campaign stands and why its arms end where they do: `macb reproduce --status`
and the page's header, its Why table, its claims per seed and fig8's 75% band, on
synthetic run folders (rows as `--local` writes them) and synthetic points.
"""

from __future__ import annotations

import gzip
import itertools
import json
import math
import os
import time
from pathlib import Path

import numpy as np
import pytest

from cli.local import expand_body, local_experiment, local_points
from cli.main import main
from cli.reproduce import analysis, render
from cli.reproduce.controls import against_control, bonus_paid, control_verdicts, distinguish
from cli.reproduce.experiments import experiment_body, select_arms
from cli.reproduce.figures import FIGURES
from cli.reproduce.status import measure, tail_rows
from tests.test_figures import synthetic

FIG8 = FIGURES["fig8"]
SPARSE = (
    "Sparse",
    "Sparse + Dis-MACB",
    "Sparse + Cen-MACB",
    "Sparse + constant beta=0.8 (control)",
)
ARGS = ("fig8", "--profile", "thesis", "--arms", "sparse*", "--seeds", "0", "1")


def _rows(arm: str, seed: int) -> list[dict]:
    """Sparse and Dis-MACB (one group) at 1,000 episodes an hour of their clock for 2 h;
    Cen-MACB and the control (the other group) 1,000 in the first hour, then 500: the
    last hour's speed is 500, not the 750 of the whole run. Cen-MACB pays beta on every
    row (every key new) and gives its control's rows exactly."""
    fast = arm in SPARSE[:2]
    episodes = np.arange(1, 2001 if fast else 1501)
    slow = np.where(episodes <= 1000, episodes * 3.6, 3600 + (episodes - 1000) * 7.2)
    wall = episodes * 3.6 if fast else slow
    success = {"Sparse": 0.1, "Sparse + Dis-MACB": 0.9}.get(arm, 0.2)
    counting = arm in SPARSE[1:3]
    dis = arm == "Sparse + Dis-MACB"
    rows = []
    for e, w in zip(episodes, wall, strict=True):
        rows.append(
            {
                "episode": int(e),
                "env_steps": int(e) * 20,
                "success_rate": success + (0.02 * seed if dis else 0.0),
                "eval_return": -20.0 + success + (0.001 * (arm == "Sparse")),
                "collisions_cum": 0,
                "count1_pct": (90.0 + 4 * seed if dis else 100.0) if counting else 0.0,
                "bonus_mean": (0.5 + 0.2 * seed if dis else 0.8) if e > 5 else 0.0,
                "bonus_std": 0.1 if dis and e > 5 else 0.0,
                "wall_s": float(w),
            }
        )
    return rows


@pytest.fixture
def runs_dir(tmp_path: Path) -> Path:
    body = select_arms(FIG8, experiment_body(FIG8, "thesis", [0, 1], None), ["sparse*"])
    _, _, runs = expand_body(body)
    for r in runs:
        folder = tmp_path / "runs" / r.name
        folder.mkdir(parents=True)
        (folder / "config.json").write_text(json.dumps(r.config.model_dump(mode="json")))
        lines = [json.dumps(row) for row in _rows(r.arm or "", r.seed)]
        (folder / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    return tmp_path / "runs"


def test_status_gives_each_run_its_episode_last_hour_speed_and_the_finish(runs_dir, capsys):
    torn = runs_dir / "Sparse-s0" / "metrics.jsonl"
    with torn.open("a") as f:
        f.write('{"episode": 2001, "wall')  # a row being written: skipped
    assert main(["reproduce", *ARGS, "--status", "--runs", str(runs_dir)]) == 0
    out = capsys.readouterr().out
    line = {x.split()[0]: x for x in out.splitlines() if x.startswith("Sparse")}
    assert "2,000 of 40,000 (5.0%)" in line["Sparse-s0"] and "1,000" in line["Sparse-s0"]
    assert "1,500 of 40,000" in line["Sparse_Cen-MACB-s1"]
    speed = line["Sparse_Cen-MACB-s1"].split("(3.8%)")[1].split()[0]
    assert speed == "500", "the last hour's speed, not the whole run's 750"
    # the figure ends with its slowest group: 38,500 episodes at 500 an hour
    assert "in 77.0 h of running" in out and "38,500 episodes left at 500/h" in out
    assert "1,500 of 40,000 episodes (per arm: Sparse 2,000;" in out
    assert "not running" not in out
    old = time.time() - 3 * 3600
    for metrics in runs_dir.glob("*/metrics.jsonl"):
        os.utime(metrics, (old, old))
    assert main(["reproduce", *ARGS, "--status", "--runs", str(runs_dir)]) == 0
    assert "the campaign is not running" in capsys.readouterr().out


def test_status_refuses_a_missing_runs_folder(tmp_path, capsys):
    assert main(["reproduce", *ARGS, "--status", "--runs", str(tmp_path / "none")]) == 2


def test_speed_is_over_the_last_hour_of_the_runs_own_clock():
    episodes = np.arange(1, 101)
    wall = np.concatenate([np.arange(1, 51) * 72.0, 3600 + np.arange(1, 51) * 144.0])
    p = measure("r", "a", 0, 1000, episodes, wall)
    assert p.episode == 100 and p.speed == pytest.approx(25.0) and p.span_h == 1.0
    assert p.hours_left == pytest.approx(900 / 25.0)
    no_clock = measure("r", "a", 0, 1000, episodes, np.full(100, math.nan))
    assert no_clock.episode == 100 and no_clock.speed is None


def test_the_page_says_how_far_why_and_each_seed(runs_dir, tmp_path):
    out = tmp_path / "page"
    got = main(["reproduce", *ARGS, "--report-only", "--runs", str(runs_dir), "--out", str(out)])
    assert got == 1  # incomplete runs: the page is written, the exit says so
    md = (out / "fig8.md").read_text()
    header = md.split("## Arms")[0]
    assert "- Progress (page built " in header
    assert "1,500 of 40,000 episodes (per arm: Sparse 2,000; Sparse + Dis-MACB 2,000;" in header
    assert "in 77.0 h of running" in header and "75% confidence interval" in header
    why = md.split("## Why")[1].split("\n## ")[0]
    rows = {r.split(" | ")[0][2:]: r for r in why.splitlines() if r.startswith("| Sparse")}
    dis, cen = rows["Sparse + Dis-MACB"], rows["Sparse + Cen-MACB"]
    assert "| 92% (s0 90%, s1 94%) |" in dis  # count-1 %, mean then per seed
    # pooled over both seeds' rows: mean 0.6, spread sqrt(0.1^2 + 0.1^2)
    assert "0.600 ± 0.141 (s0 0.500 ± 0.100, s1 0.700 ± 0.100)" in dis
    assert "distinguishable: above the control" in dis and "not run to that length" in dis
    assert "0.800 ± 0.000 (a constant shift: every sampled key new)" in cen
    assert "the same runs as the control, point for point (as far as both went: 1,500 of" in cen
    assert "not run to that length" not in cen, "equal points are a fact at any length"
    claims = md.split("## Claims")[1].split("\n## ")[0]
    (dis_claim,) = [x for x in claims.splitlines() if "around 70%" in x]
    assert "s0: 90% at 2,000; s1: 92% at 2,000" in dis_claim
    assert dis_claim.endswith("| **not run to that length** |")
    assert "**beats the control" not in md.split("## Against the control")[1]
    # only the arms selected ('sparse*'): no 0 for the dense arms without runs
    assert "these runs reached 1,500, 2,000 episodes." in header
    # the command that rebuilds and resumes these runs names their selection
    rebuild = f"fig8 --local --profile thesis --seeds 0 1 --runs {runs_dir} --arms 'sparse*'`"
    assert f"`macb reproduce {rebuild}" in md, "its selection and its folder"
    assert "- Restarts:" not in header, "no provenance, nothing said"
    assert not (out / "fig8.csv").exists()
    with gzip.open(out / "fig8.csv.gz", "rt") as f:
        assert sum(1 for _ in f) == 1 + 2 * (2000 + 2000 + 1500 + 1500)
    first = (out / "fig8.csv.gz").read_bytes()
    main(["reproduce", *ARGS, "--report-only", "--runs", str(runs_dir), "--out", str(out)])
    assert (out / "fig8.csv.gz").read_bytes() == first, "the same points, the same bytes"


def _start(commit: str, started: str, resumed_at: int | None = None) -> dict:
    start = {"started": started, "role": "group", "code": {"commit": commit, "dirty": False}}
    return start if resumed_at is None else {**start, "resumed_at": resumed_at}


def test_the_page_header_says_how_often_and_where_the_campaign_resumed(runs_dir, tmp_path):
    """Each run's provenance.json holds a start per resume with the episode it went on
    from: resumes within minutes of each other are one restart of the campaign (its
    groups at their own cuts, even when one group's first attempt was stopped and
    given again). Starts written before `resumed_at` say so."""
    for folder in runs_dir.iterdir():
        first = folder.name.startswith(("Sparse-", "Sparse_Dis"))
        at = 1000 if first else 1200
        starts = [
            _start("a" * 40, "2026-12-04T08:00:00Z"),
            _start("b" * 40, "2026-12-04T20:00:00Z"),  # before resumes were recorded
            *([_start("c" * 40, "2026-12-05T08:58:00Z", at)] if first else []),  # stopped
            _start("c" * 40, "2026-12-05T09:00:00Z" if first else "2026-12-05T09:01:00Z", at),
        ]
        (folder / "provenance.json").write_text(json.dumps({"starts": starts}))
    out = tmp_path / "page"
    main(["reproduce", *ARGS, "--report-only", "--runs", str(runs_dir), "--out", str(out)])
    header = (out / "fig8.md").read_text().split("## Arms")[0]
    assert (
        "- Restarts: resumed 2 times (at episodes ? (code bbbbbbbbbbbb, 2026-12-04T20:00:00Z); "
        "1,000 and 1,200 (code cccccccccccc, 2026-12-05T08:58:00Z)); ?: a resume written "
        "before its episode was recorded."
    ) in header


def _page_of_starts(runs_dir: Path, out: Path, starts_of) -> str:
    """Every run folder's provenance.json set to `starts_of(i)` (its starts, the folders
    in name order), then the page built: its header (all before `## Arms`)."""
    for i, folder in enumerate(sorted(runs_dir.iterdir())):
        (folder / "provenance.json").write_text(json.dumps({"starts": starts_of(i)}))
    main(["reproduce", *ARGS, "--report-only", "--runs", str(runs_dir), "--out", str(out)])
    return (out / "fig8.md").read_text().split("## Arms")[0]


def test_a_campaign_resumed_on_another_cpu_says_which_cpu_computed_which_rows(runs_dir, tmp_path):
    """The same code rounds differently on another kind of CPU: a campaign that moves
    between machines names every start's CPU (What ran lists them all and how many runs
    crossed, from which first CPU; each restart names its own), and the page's runs
    record keeps them for `macb results --compare`."""

    def moved(first_cpu: str) -> list[dict]:
        return [
            {**_start("c" * 40, "2026-12-05T09:00:00Z"), "machine": {"cpu": first_cpu}},
            {**_start("c" * 40, "2026-12-05T13:00:00Z", 500), "machine": {"cpu": "EPYC Y"}},
        ]

    out = tmp_path / "page"
    header = _page_of_starts(runs_dir, out, lambda i: moved("Xeon X"))
    n = len(list(runs_dir.iterdir()))
    assert (
        f"; CPU EPYC Y, Xeon X ({n} run(s) started on Xeon X and resumed on another CPU:"
    ) in header
    assert "at episodes 500 (code cccccccccccc, CPU EPYC Y, 2026-12-05T13:00:00Z)" in header
    record = json.loads((out / "fig8-runs.json").read_text())
    assert {tuple(r["start_cpus"]) for r in record["runs"] if r["start_cpus"]} == {
        ("Xeon X", "EPYC Y")
    }
    # One run moved, the others on EPYC Y throughout: only the one that moved is counted,
    # and only the CPU it started on is named as a start.
    header = _page_of_starts(runs_dir, out, lambda i: moved("Xeon X" if i == 0 else "EPYC Y"))
    assert "; CPU EPYC Y, Xeon X (1 run(s) started on Xeon X and resumed on another CPU:" in header
    # One CPU throughout: no note of a crossing.
    one = [{**_start("c" * 40, "2026-12-05T09:00:00Z"), "machine": {"cpu": "Xeon X"}}]
    header = _page_of_starts(runs_dir, out, lambda i: one)
    assert "; CPU Xeon X; code cccccccccccc." in header and "another CPU" not in header


def test_a_campaign_restarted_on_newer_code_names_every_starts_code(runs_dir, tmp_path):
    """What ran names the code of every start, not only the latest's: a campaign that
    went on from its cuts on a newer checkout ran its first rows with the older one."""
    starts = [
        {**_start("a" * 40, "2026-12-05T09:00:00Z"), "machine": {"cpu": "Xeon X"}},
        {**_start("b" * 40, "2026-12-05T13:00:00Z", 500), "machine": {"cpu": "Xeon X"}},
    ]
    out = tmp_path / "page"
    header = _page_of_starts(runs_dir, out, lambda i: starts)
    n = len(list(runs_dir.iterdir()))
    assert (
        f"; code aaaaaaaaaaaa, bbbbbbbbbbbb ({n} run(s) resumed on other code than they "
        "started with: the Restarts line"
    ) in header
    assert "at episodes 500 (code bbbbbbbbbbbb, CPU Xeon X" in header
    record = json.loads((out / "fig8-runs.json").read_text())
    assert {
        tuple(c["commit"] for c in r["start_codes"]) for r in record["runs"] if r["start_codes"]
    } == {("a" * 40, "b" * 40)}


def test_one_commands_starts_hours_apart_are_one_restart_and_two_commands_two():
    """A `--local` with more groups than `--jobs` starts its later groups hours after its
    first: the starts name their command, so they are one restart; another command is
    another restart however close (beyond RESTART_GAP_S), and one begun within it of
    the last is the same restart (stopped and given again at once)."""

    def resume(started: str, episode: int, command: str | None) -> dict:
        return {"episode": episode, "code": {"commit": "c" * 40}, "started": started,
                "command": command}  # fmt: skip

    runs = [
        {"resumes": [resume("2026-12-05T09:00:00Z", 1000, "x")]},
        {"resumes": [resume("2026-12-05T13:00:00Z", 1200, "x")]},  # the same command
        {"resumes": [resume("2026-12-05T09:05:00Z", 900, "y")]},  # given again at once
        {"resumes": [resume("2026-12-05T20:00:00Z", 2000, "z")]},
    ]
    line = render.restarts(runs)[0]
    assert line.startswith("- Restarts: resumed 2 times (at episodes 900 and 1,000 and 1,200")
    assert "; 2,000 (code cccccccccccc, 2026-12-05T20:00:00Z))." in line
    # without command names (older starts) the hours-later group is a restart of its own
    for r in runs:
        r["resumes"][0]["command"] = None
    assert render.restarts(runs)[0].startswith("- Restarts: resumed 3 times")


def test_a_local_command_names_itself_in_every_start_it_makes(tmp_path, monkeypatch):
    """Each `run_groups` call stamps one command id into every run's start, whichever
    group and process trained it; a Slurm array's tasks share their job's (a requeue,
    SLURM_RESTART_COUNT, is another)."""
    from cli.local import LocalRun, command_id, run_groups
    from shared.config import make_config

    base = {"task": "simple", "algo": "ddpg", "hidden": [16, 16], "episode_len": 5,
            "episodes": 2, "eval_every": 2, "eval_episodes": 1, "learning_starts": 10,
            "batch_size": 4, "learner_lanes": 1, "threads": 1}  # fmt: skip
    runs = [
        LocalRun("a", None, 1, make_config({**base, "seed": 1})),
        LocalRun("b", None, 2, make_config({**base, "seed": 2, "k": 8})),
    ]
    out = tmp_path / "runs"
    assert run_groups(runs, out, quiet=True, max_runs=1, jobs=2) == 0  # two processes

    def commands(name: str) -> list:
        starts = json.loads((out / name / "provenance.json").read_text())["starts"]
        return [s.get("command") for s in starts]

    first = commands("a")
    assert len(first) == 1 and isinstance(first[0], str) and commands("b") == first
    assert command_id() != first[0]  # another call: another process or second
    monkeypatch.setenv("SLURM_ARRAY_JOB_ID", "4242")
    monkeypatch.delenv("SLURM_RESTART_COUNT", raising=False)
    assert command_id() == "slurm-4242-0"
    monkeypatch.setenv("SLURM_RESTART_COUNT", "1")
    assert command_id() == "slurm-4242-1"


def test_fig8_draws_the_bootstrap_75_percent_band_and_seeds_average_to_the_mean():
    shapes = {"Sparse": (30000, 0.45), "Sparse + Dis-MACB": (20000, 0.7)}
    exp, points = synthetic(FIG8, shapes, 40000, seeds=(0, 1, 2), step=200)
    a = analysis.analyse(FIG8, exp, points)
    arm = a.arm("Sparse + Dis-MACB")
    lo, hi = arm.band()
    stack = arm.smoothed["success_rate"]
    i = len(arm.episodes) - 1
    means = [np.mean([stack[j, i] for j in pick]) for pick in itertools.product(range(3), repeat=3)]
    assert lo[i] == pytest.approx(np.percentile(means, 12.5))
    assert hi[i] == pytest.approx(np.percentile(means, 87.5))
    assert not np.allclose(hi, arm.mean["success_rate"] + arm.std["success_rate"])
    assert "the band the thesis draws" in render.markdown(a, "thesis")
    v, _ = arm.value_at(40000)
    per_seed = [a.for_seed(s).arm(arm.name).value_at(40000)[0] for s in (0, 1, 2)]
    assert np.mean(per_seed) == pytest.approx(v)
    control = a.arm("Sparse + constant beta=0.8 (control)")
    assert against_control(a, arm, control).startswith("distinguishable: above the control")
    # a control a hair above the arm, inside its spread: not told apart
    run_of = {(r["arm"], r["seed"]): r["id"] for r in exp["runs"]}
    for s in (0, 1, 2):
        mine = points[run_of[("Sparse + Dis-MACB", s)]]
        points[run_of[("Sparse + constant beta=0.8 (control)", s)]] = [
            {**p, "success_rate": p["success_rate"] + 1e-3, "eval_return": 0.0} for p in mine
        ]
    b = analysis.analyse(FIG8, exp, points)
    verdict = against_control(b, b.arm(arm.name), b.arm(control.name))
    assert verdict.startswith("not distinguishable: the spreads overlap")
    # the Against the control section by the same rule, though the control ends higher
    controls = {c[0]: c[4] for c in control_verdicts(b)}
    assert controls[arm.name] == "not distinguishable from the control"
    short = {k: v[:100] for k, v in points.items()}  # 20,000 of 40,000 episodes
    c = analysis.analyse(FIG8, exp, short)
    assert {x[0]: x[4] for x in control_verdicts(c)}[arm.name] == (
        "not run to that length (20,000 of 40,000 episodes); not distinguishable so far"
    )
    assert "so far: not distinguishable" in against_control(c, c.arm(arm.name), c.arm(control.name))


def test_bonus_paid_is_none_before_updates_and_pools_the_rows():
    assert bonus_paid([{"bonus_mean": np.zeros(3), "bonus_std": np.zeros(3)}]) is None
    paid = bonus_paid([{"bonus_mean": np.array([0.0, 0.4, 0.8]), "bonus_std": np.zeros(3)}])
    assert paid is not None and paid.mean == pytest.approx(0.6)
    assert paid.spread == pytest.approx(0.2)  # the 0 before updates left out: 0.4, 0.8


def test_the_last_hour_is_read_from_the_end_of_a_long_file(tmp_path):
    """Blocks from the end, grown until a row an hour of clock back is in them; a cut
    first line of a block is not taken for a row."""
    path = tmp_path / "metrics.jsonl"
    rows = ({"episode": e, "wall_s": float(e), "pad": "x" * 300} for e in range(1, 5001))
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    got = tail_rows(path)
    assert [r["episode"] for r in got] == list(range(1400, 5001))
    short = tmp_path / "short.jsonl"
    short.write_text("".join(json.dumps({"episode": e, "wall_s": e * 10.0}) + "\n" for e in (1, 2)))
    assert [r["episode"] for r in tail_rows(short)] == [1, 2]  # under an hour: all of it


def test_an_arm_that_learns_sooner_to_the_same_end_is_told_apart_by_its_area():
    """Both end at 100%, so their last points overlap; the counting arm gets there at
    8,000 episodes and its control at 25,000: the whole run parts them (each seed's mean
    over the episodes both ran), and both sections say so by the one rule."""
    shapes = {
        "Sparse + Cen-MACB": (8000, 1.0),
        "Sparse + constant beta=0.8 (control)": (25000, 1.0),
    }
    exp, points = synthetic(FIG8, shapes, 40000, seeds=(0, 1, 2), step=200)
    for rows in points.values():  # both at the plateau from 30,000 on, to the last bit
        for p in rows:
            if p["episode"] >= 30000 and p["success_rate"] > 0.99:
                p["success_rate"] = 1.0
    a = analysis.analyse(FIG8, exp, points)
    arm, control = a.arm("Sparse + Cen-MACB"), a.arm("Sparse + constant beta=0.8 (control)")
    d = distinguish(arm, control)
    assert d is not None and (d.side, d.by) == ("above", "area") and d.up == 0.0
    assert against_control(a, arm, control).startswith(
        "distinguishable: above the control over the run"
    )
    assert {c[0]: c[4] for c in control_verdicts(a)}["Sparse + Cen-MACB"] == "beats the control"
    # the control's seeds learning as the arm's do (its seeds' curves, in another order):
    # one spread over the run, and at the end
    run_of = {(r["arm"], r["seed"]): r["id"] for r in exp["runs"]}
    for s in (0, 1, 2):
        mine = points[run_of[("Sparse + Cen-MACB", (s + 1) % 3)]]
        points[run_of[(control.name, s)]] = [{**p, "eval_return": 0.0} for p in mine]
    b = analysis.analyse(FIG8, exp, points)
    d = distinguish(b.arm(arm.name), b.arm(control.name))
    assert d is not None and (d.side, d.by) == ("overlap", "end")


def _analysis(runs_dir: Path, episodes: int) -> analysis.Analysis:
    """The sparse arms of `runs_dir` as the report reads them, their runs started for
    `episodes` episodes."""
    body = select_arms(FIG8, experiment_body(FIG8, "thesis", [0, 1], episodes), ["sparse*"])
    name, seeds, runs = expand_body(body)
    for r in runs:  # the folders' configs say the same length as the experiment's
        (runs_dir / r.name / "config.json").write_text(json.dumps(r.config.model_dump(mode="json")))
    exp = local_experiment(name, seeds, runs, runs_dir)
    points = {k: analysis.columns(v) for k, v in local_points(runs, runs_dir).items()}
    return analysis.analyse(FIG8, exp, points)


def test_the_plot_marks_each_value_the_thesis_states_where_the_runs_will_reach_it(
    runs_dir, tmp_path
):
    from cli.reproduce import plot

    full = _analysis(runs_dir, 40000)  # a campaign at 2,000 of 40,000 episodes
    assert [(n, c.arm, c.episode) for n, _, c in plot.thesis_marks(full)] == [
        (1, "Sparse", 40000),
        (2, "Sparse + Dis-MACB", 40000),
        (3, "Sparse + Cen-MACB", 15000),
    ]
    fig, _ = plot.draw(full, "thesis")
    (ax,) = fig.axes
    assert ax.get_xlim()[1] >= 40000, "the whole length drawn: how far the runs got"
    drawn = {(t.get_text(), t.xy) for t in ax.texts}
    assert ("thesis, claim 3: 100% at 1.5e4", (15000, 0.95)) in drawn
    assert ("thesis, claim 1: just over 40% at 4e4", (40000, 0.45)) in drawn
    out = tmp_path / "page"
    main(["reproduce", *ARGS, "--report-only", "--runs", str(runs_dir), "--out", str(out)])
    assert "a hollow diamond marks each value a claim states" in (out / "fig8.md").read_text()

    short = _analysis(runs_dir, 1500)  # runs started for 1,500: no claim is within reach
    assert plot.thesis_marks(short) == []
    fig, _ = plot.draw(short, "thesis")
    assert len(fig.axes[0].texts) == 0 and fig.axes[0].get_xlim()[1] < 2500
    main(["reproduce", *ARGS, "--episodes", "1500", "--report-only", "--runs", str(runs_dir),
          "--out", str(out)])  # fmt: skip
    assert "hollow diamond" not in (out / "fig8.md").read_text()


def test_arms_not_started_are_named_not_counted_as_the_figures_progress(runs_dir, tmp_path, capsys):
    """The campaign runs the sparse arms, then the dense ones: a page of every arm while
    the dense ones wait gives the progress of the arms started and names the rest, not
    "0 of 40,000", and projects the started runs' finish."""
    every = ("fig8", "--profile", "thesis", "--arms", "*", "--seeds", "0", "1")
    assert main(["reproduce", *every, "--status", "--runs", str(runs_dir)]) == 0
    out = capsys.readouterr().out
    dense = "Distance, Distance + Cen-MACB (beta=0.1), Distance + constant beta=0.1 (control)"
    figure = [x for x in out.splitlines() if x.startswith("figure: ")][0]
    assert figure.startswith("figure: 1,500 of 40,000 episodes in the 4 arm(s) started (per")
    assert f"not started: {dense} (6 run(s))" in figure
    assert "of the runs started, in 77.0 h of running" in figure
    assert figure.endswith("then 6 run(s) not started, not projected")
    assert main(["reproduce", *every, "--report-only", "--runs", str(runs_dir),
                 "--out", str(tmp_path / "page")]) == 1  # fmt: skip
    md = (tmp_path / "page" / "fig8.md").read_text()
    header = md.split("## Arms")[0]
    assert "these runs reached 1,500, 2,000 episodes (3 arm(s) not started)." in header
    assert "1,500 of 40,000 episodes in the 4 arm(s) started" in header
    assert "counted from the build; then 6 run(s) not started, not projected." in header
    reported = {"live": {"provenance": {"learner": {"precision": "fp32"}}}}
    line = render.what_ran([{"id": "a", **reported}, {"id": "b"}, {"id": "c"}], {"a", "b"})
    assert line.endswith("; 1 run(s) reported none; 1 run(s) not started."), line
    why = md.split("## Why")[1].split("\n## ")[0]
    (waiting,) = [r for r in why.splitlines() if r.startswith("| Distance + Cen-MACB")]
    assert "| - | - | none paid yet |" in waiting, "no per-seed cells for runs not started"
    claims = md.split("## Claims")[1].split("\n## ")[0]
    (dense,) = [x for x in claims.splitlines() if "dense reward setting" in x]
    assert "| no points | no points | **not run to that length** |" in dense


def test_an_arm_some_of_whose_seeds_started_is_started(runs_dir, tmp_path):
    """Runs start one by one (the API's queue): an arm with one seed's rows is started,
    at the least its seeds reached (0), not listed with the arms not started."""
    every = ("fig8", "--profile", "thesis", "--arms", "*", "--seeds", "0", "1")
    body = select_arms(FIG8, experiment_body(FIG8, "thesis", [0, 1], None), ["*"])
    (one,) = [r for r in expand_body(body)[2] if r.arm == "Distance" and r.seed == 0]
    folder = runs_dir / one.name
    folder.mkdir()
    (folder / "config.json").write_text(json.dumps(one.config.model_dump(mode="json")))
    rows = [json.dumps(row) for row in _rows("Sparse", 0)[:100]]
    (folder / "metrics.jsonl").write_text("\n".join(rows) + "\n")
    assert main(["reproduce", *every, "--report-only", "--runs", str(runs_dir),
                 "--out", str(tmp_path / "page")]) == 1  # fmt: skip
    header = (tmp_path / "page" / "fig8.md").read_text().split("## Arms")[0]
    assert "these runs reached 0, 1,500, 2,000 episodes (2 arm(s) not started)." in header
    assert "0 of 40,000 episodes in the 5 arm(s) started" in header
    assert "not started: Distance + Cen-MACB (beta=0.1), Distance + constant beta=0.1" in header
    record = json.loads((tmp_path / "page" / "fig8-claims.json").read_text())
    assert record["episodes_reached"] == 0 and len(record["arms_not_started"]) == 2


def test_a_figure_none_of_whose_runs_started_says_so_and_so_between_two_turns():
    from cli.reproduce.status import FigureProgress, RunProgress

    runs = [RunProgress(f"r{i}", "a", i, 100) for i in range(2)]
    progress = FigureProgress(runs, 100)
    assert progress.reached() == "0 of 100 episodes"
    assert progress.finish(0.0) == "no projection: no run has started (2 to run)"
    # the first turn's arm done, the next one's not started
    split = FigureProgress(
        [RunProgress("r0", "a", 0, 100, episode=100), RunProgress("r1", "b", 0, 100)], 100
    )
    assert (
        split.reached() == "100 of 100 episodes in the 1 arm(s) started; not started: b (1 run(s))"
    )
    assert split.finish(0.0) == (
        "the runs started are finished; 1 run(s) not started, not projected"
    )
