"""The Python API (macb/, docs/python.md): a runs folder as a DataFrame, and a figure's
summary from it equal to what the report writes for the same runs, on synthetic run
folders as `macb reproduce --local` writes them (tests/test_fig8_page.py's rows).
"""

from __future__ import annotations

import json
import re
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import macb
from cli.local import expand_body, local_experiment, local_points
from cli.main import main
from cli.reproduce.analysis import analyse, columns
from cli.reproduce.experiments import experiment_body, select_arms
from cli.reproduce.figures import FIGURES
from services.api.store import Store
from shared.net.messages import Assignment
from tests.harness import TINY, row, start_api
from tests.test_fig8_page import _rows

ROOT = Path(__file__).resolve().parent.parent
FIG8 = FIGURES["fig8"]
ARGS = ("fig8", "--profile", "thesis", "--arms", "sparse*", "--seeds", "0", "1")


def _body() -> dict:
    return select_arms(FIG8, experiment_body(FIG8, "thesis", [0, 1], None), ["sparse*"])


@pytest.fixture
def out(tmp_path: Path) -> Path:
    """A reproduce OUT: its runs/ as --local writes them (no page yet)."""
    _, _, runs = expand_body(_body())
    for r in runs:
        folder = tmp_path / "fig8-thesis" / "runs" / r.name
        folder.mkdir(parents=True)
        (folder / "config.json").write_text(json.dumps(r.config.model_dump(mode="json")))
        lines = [json.dumps(row) for row in _rows(r.arm or "", r.seed)]
        (folder / "metrics.jsonl").write_text("\n".join(lines) + "\n")
    return tmp_path / "fig8-thesis"


def test_a_runs_folder_is_one_row_per_point_with_its_run_arm_seed_and_config(out):
    frame = macb.load_runs(out)
    assert list(frame.columns[:4]) == ["run", "arm", "seed", "episode"]
    assert sorted(frame["run"].unique()) == [
        "Sparse-s0",
        "Sparse-s1",
        "Sparse_Cen-MACB-s0",
        "Sparse_Cen-MACB-s1",
        "Sparse_Dis-MACB-s0",
        "Sparse_Dis-MACB-s1",
        "Sparse_constant_beta_0.8_control-s0",
        "Sparse_constant_beta_0.8_control-s1",
    ]
    assert len(frame) == 4 * 2000 + 4 * 1500  # every row of every run, none twice
    one = frame[frame["run"] == "Sparse_Dis-MACB-s1"]
    assert one["arm"].unique().tolist() == ["Sparse_Dis-MACB"]  # no page yet: the folder's
    assert one["seed"].unique().tolist() == [1] and one["config.seed"].unique().tolist() == [1]
    assert one["episode"].tolist() == list(range(1, 2001))
    assert one["success_rate"].iloc[0] == pytest.approx(0.92)
    assert one["config.episodes"].unique().tolist() == [40_000]
    # config keys never shadow a metric: episodes (config) beside episode (row)
    assert all(
        c.startswith("config.") for c in frame.columns[frame.columns.get_loc("wall_s") + 1 :]
    )


def test_a_torn_last_line_is_skipped_and_bad_files_are_refused_by_name(out):
    runs = out / "runs"
    with (runs / "Sparse-s0" / "metrics.jsonl").open("a") as f:
        f.write('{"episode": 2001, "wall')  # a row being written
    frame = macb.load_runs(runs)
    assert frame[frame["run"] == "Sparse-s0"]["episode"].max() == 2000
    bad = runs / "Sparse-s1" / "metrics.jsonl"
    lines = bad.read_text().splitlines()
    bad.write_text("\n".join([lines[0], "{not json", *lines[1:]]) + "\n")
    with pytest.raises(macb.RunsError, match=r"s1/metrics.jsonl: line 2: not a metric row"):
        macb.load_runs(runs)
    bad.write_bytes(lines[0].encode() + b'\n{"episode": \xff\xfe}\n' + lines[1].encode() + b"\n")
    with pytest.raises(macb.RunsError, match=r"s1/metrics.jsonl: line 2: not a metric row"):
        macb.load_runs(runs)  # bytes that are not UTF-8
    bad.write_bytes(("\n".join(lines) + "\n").encode() + b'{"episode": \xff\xfe}\n')
    frame = macb.load_runs(runs)  # a last line that does not read: torn, left out
    assert (frame["run"] == "Sparse-s1").sum() == len(lines)
    bad.write_text("\n".join(lines) + "\n")
    (runs / "Sparse-s1" / "config.json").write_text('{"seed": 1,')
    with pytest.raises(macb.RunsError, match=r"Sparse-s1/config.json: unreadable"):
        macb.load_runs(out)
    (runs / "Sparse-s1" / "config.json").unlink()
    with pytest.raises(macb.RunsError, match=r"Sparse-s1/config.json: missing"):
        macb.load_runs(out)


def test_no_runs_is_a_clear_error(tmp_path):
    with pytest.raises(macb.RunsError, match="no such folder"):
        macb.load_runs(tmp_path / "absent")
    (tmp_path / "empty" / "x").mkdir(parents=True)
    with pytest.raises(macb.RunsError, match=r"empty: no runs"):
        macb.load_runs(tmp_path / "empty")


def test_train_runs_one_folder_seeds_and_a_csv_only_run(tmp_path):
    """`macb train --out DIR` (DIR is the run) and `--seeds` (DIR/seed-S, one arm named
    by DIR); metrics.csv is read when there is no metrics.jsonl."""
    for seed in (3, 4):
        folder = tmp_path / "beta06" / f"seed-{seed}"
        folder.mkdir(parents=True)
        (folder / "config.json").write_text(json.dumps({"seed": seed, "beta": 0.6}))
        (folder / "metrics.csv").write_text(
            "episode,success_rate,eval_return\n10,0.5,-3\n20,,-2.5\n30,0.7"
        )  # the last line is being written: fewer cells than the header
    frame = macb.load_runs(tmp_path / "beta06")
    assert frame["arm"].unique().tolist() == ["beta06"]
    assert frame["seed"].tolist() == [3, 3, 4, 4]
    assert frame["episode"].tolist() == [10, 20, 10, 20]
    assert np.isnan(frame["success_rate"].iloc[1]) and frame["config.beta"].iloc[0] == 0.6
    single = macb.load_runs(tmp_path / "beta06" / "seed-4")
    assert single["run"].unique().tolist() == ["seed-4"] and len(single) == 2


def test_a_csv_row_torn_inside_its_last_cell_is_skipped_and_bad_side_files_are_named(tmp_path):
    """A last CSV line without its newline is a row being written, even with all its
    cells (the tear cut its last number); a root metrics.csv that is not text, a runs
    record whose runs are not objects and a row whose episode is no whole number are
    refused with RunsError naming the file (not a decode or type error)."""
    folder = tmp_path / "out" / "runs" / "a-s0"
    folder.mkdir(parents=True)
    (folder / "config.json").write_text(json.dumps({"seed": 0}))
    (folder / "metrics.csv").write_text("episode,wall_s\n10,12.5\n20,1437.17")  # torn: 1437.17...
    frame = macb.load_runs(tmp_path / "out")
    assert frame["episode"].tolist() == [10] and frame["wall_s"].tolist() == [12.5]
    (folder / "metrics.csv").write_text("episode,wall_s\n10,12.5\n20,1437.17\n")
    assert macb.load_runs(tmp_path / "out")["wall_s"].tolist() == [12.5, 1437.17]
    (folder / "metrics.csv").write_text("episode,wall_s\n10,12.5\nten,3\n")
    with pytest.raises(macb.RunsError, match=r"a-s0/metrics.csv: row 2 has episode 'ten'"):
        macb.load_runs(tmp_path / "out")
    (folder / "metrics.csv").unlink()
    (folder / "metrics.jsonl").write_text('{"episode": 10}\n{"episode": null}\n{"episode": 30}\n')
    with pytest.raises(macb.RunsError, match=r"a-s0/metrics.jsonl: row 2 has episode None"):
        macb.load_runs(tmp_path / "out")
    assert main(["view", str(tmp_path / "out"), "--port", "0"]) == 2  # refused, not a traceback
    (folder / "metrics.jsonl").write_text('{"episode": 10}\n')
    record = tmp_path / "out" / "fig8-runs.json"
    record.write_text(json.dumps({"runs": ["a-s0"]}))
    with pytest.raises(macb.RunsError, match=r"fig8-runs.json: not a reproduce runs record"):
        macb.load_runs(tmp_path / "out")
    record.unlink()
    (tmp_path / "out" / "metrics.csv").write_bytes(b"run,arm\n\xff\xfe,x\n")
    with pytest.raises(macb.RunsError, match=r"out/metrics.csv: unreadable"):
        macb.load_runs(tmp_path / "out")


def test_a_macb_run_out_folder_names_each_runs_arm(tmp_path):
    """`macb run --out DIR` of several runs: DIR/<run id>/ each, and the experiment's
    metrics.csv (arm, seed, run columns) in DIR, which is not a run."""
    for run, seed in (("r1", 0), ("r2", 1)):
        folder = tmp_path / run
        folder.mkdir()
        (folder / "config.json").write_text(json.dumps({"seed": seed}))
        (folder / "metrics.jsonl").write_text(json.dumps({"episode": 4}) + "\n")
    (tmp_path / "metrics.csv").write_text(
        "arm,seed,run,episode\nno bonus,0,r1,4\nCen-MACB,1,r2,4\n"
    )
    frame = macb.load_runs(tmp_path)
    assert frame[["run", "arm"]].values.tolist() == [["r1", "no bonus"], ["r2", "Cen-MACB"]]


def _table(md: str, section: str, first: str) -> list[list[str]]:
    body = md.split(f"## {section}")[1].split("\n## ")[0]
    rows = [r for r in body.splitlines() if r.startswith("| ") and not r.startswith(first)]
    return [[c.strip() for c in r.strip().strip("|").split(" | ")] for r in rows]


def test_the_summary_of_a_frame_is_what_the_report_writes_for_the_same_runs(out):
    code = main(["reproduce", *ARGS, "--report-only", "--out", str(out)])
    assert code == 1  # incomplete runs: the page is written, the exit says so
    md = (out / "fig8.md").read_text()
    record = json.loads((out / "fig8-claims.json").read_text())
    frame = macb.load_runs(out)  # the page's fig8-runs.json names the arms now
    assert "Sparse + Dis-MACB" in set(frame["arm"])
    s = macb.summary(frame, "fig8")
    by_folder = macb.summary(macb.load_runs(out / "runs"), "fig8")  # arms from folder names
    for got in (s, by_folder):
        claims = got.claims[["measured", "verdict"]].to_dict("records")
        assert claims == [
            {"measured": c["measured"], "verdict": c["verdict"]} for c in record["claims"]
        ]
        controls = [
            [r.arm, r.control or "-", r.arm_measured, r.control_measured, f"**{r.verdict}**"]
            for r in got.controls.itertuples()
        ]
        assert controls == _table(md, "Against the control", "| MACB arm")
        why = [[*r[:5], f"**{r[5]}**"] for r in got.why.itertuples(index=False)]
        assert why == _table(md, "Why", "| counting arm")
        arms = {r[0]: r[4] for r in _table(md, "Arms", "| arm |") if r[0] in got.arms.index}
        assert got.arms["measured"].dropna().to_dict() == arms
    assert s.controls["verdict"].iloc[-1] == "no points"  # an arm not run, as on the page
    dis = s.why.set_index("arm").loc["Sparse + Dis-MACB"]
    assert "distinguishable: above the control" in dis["verdict"]
    assert s.arms.loc["Sparse + Dis-MACB", "episodes"] == 2000
    # the curves are the report's own numbers, bit for bit
    _, _, runs = expand_body(_body())
    exp = local_experiment("x", [0, 1], runs, out / "runs")
    report = analyse(
        FIG8, exp, {k: columns(v) for k, v in local_points(runs, out / "runs").items()}
    )
    for name, arm in report.arms.items():
        mine = s.curves[s.curves["arm"] == name]
        assert np.array_equal(mine["episode"].to_numpy(), arm.episodes)
        assert np.array_equal(mine["mean"].to_numpy(), arm.curve())
        low, high = arm.band()
        assert np.array_equal(mine["low"].to_numpy(), low)
        assert np.array_equal(mine["high"].to_numpy(), high)
        assert s.arms.loc[name, "plateau"] == arm.plateau or np.isnan(arm.plateau)


def test_a_frame_of_another_figure_or_an_unknown_figure_is_refused(out):
    frame = macb.load_runs(out)
    with pytest.raises(ValueError, match="no figure 'fig99'"):
        macb.summary(frame, "fig99")
    with pytest.raises(macb.RunsError, match=r"no run of the frame is an arm of fig3"):
        macb.summary(frame, "fig3")


def test_a_run_named_as_an_arm_but_of_another_config_is_refused_naming_it(out):
    """An arm is matched by name, so a run of the same name from another figure or
    another config (another task, algorithm, beta, ...) would be summarised as the arm:
    refused as `--report-only` refuses it, naming the run and the key. What reproduce's
    flags change (episodes) is not a mismatch."""
    folder = out / "runs" / "Sparse_Dis-MACB-s1"
    config = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**config, "episodes": 7}))
    assert macb.summary(macb.load_runs(out), "fig8").arms.loc["Sparse + Dis-MACB", "runs"] == 2
    (folder / "config.json").write_text(json.dumps({**config, "beta": 0.2}))
    with pytest.raises(
        macb.RunsError,
        match=r"run Sparse_Dis-MACB-s1 is not fig8's arm 'Sparse \+ Dis-MACB': "
        r"beta: 0\.2 in the run, 0\.8 in the arm",
    ):
        macb.summary(macb.load_runs(out), "fig8")


def test_a_run_without_a_row_yet_changes_no_other_runs_columns(out):
    """A run started but not evaluated yet has no row (a row is a point); its empty
    frame must not turn the other runs' integer columns into floats."""
    whole = macb.load_runs(out)
    (out / "runs" / "Sparse-s1" / "metrics.jsonl").write_text("")
    frame = macb.load_runs(out)
    assert "Sparse-s1" not in set(frame["run"])
    assert len(frame) == len(whole) - int((whole["run"] == "Sparse-s1").sum())
    for column in ("episode", "env_steps", "config.seed", "config.episodes"):
        assert frame[column].dtype == whole[column].dtype == np.int64, column
    assert macb.summary(frame, "fig8").arms.loc["Sparse", "runs"] == 1


def _code_blocks(doc: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", doc.read_text(), flags=re.S)


def test_the_docs_example_runs_against_a_runs_folder(out, capsys):
    main(["reproduce", *ARGS, "--report-only", "--out", str(out)])
    capsys.readouterr()
    blocks = [b for b in _code_blocks(ROOT / "docs" / "python.md") if "macb.Client" not in b]
    assert len(blocks) >= 3
    scope: dict = {}
    for block in blocks:
        exec(block.replace("runs/reproduce/fig8-thesis", str(out)), scope)  # noqa: S102
    assert isinstance(scope["frame"], pd.DataFrame) and isinstance(scope["s"], macb.FigureSummary)
    printed = capsys.readouterr().out
    assert "Sparse + Dis-MACB" in printed and "not run to that length" in printed


# ---------------------------------------------------------------- the API
@pytest.fixture
def api(tmp_path):
    """The API over real HTTP on 127.0.0.1 with a token, on no bus: its runs stay queued
    and their points are written into its store as the scheduler writes them."""
    server = start_api(tmp_path, None, token="s3cret")
    yield server
    server.stop()


@pytest.mark.timeout(60)
def test_start_follow_stop_and_frame_over_the_api_with_the_clis_token_rules(api, monkeypatch):
    with macb.Client(api.url, token="wrong") as bad, pytest.raises(macb.ApiError) as err:
        bad.start(TINY)
    assert err.value.status == 401 and "bearer token" in str(err.value)
    monkeypatch.setenv("MACB_API_TOKEN", "s3cret")  # no token given: the CLI's variable
    client = macb.Client(api.url)
    with pytest.raises(macb.ApiError, match="HTTP 404"):
        client.experiment_frame("nosuch")
    with pytest.raises(macb.ApiError, match="HTTP 422: beta"):
        client.start({**TINY, "beta": -1})
    exp = client.start({**TINY, "seeds": [0, 1], "grid": {"beta": [0.2, 0.8]}})
    (a, b, c, d) = (r["id"] for r in exp["runs"])
    store = Store(api.settings.db_path)  # a second connection, as the scheduler has
    store.add_points(a, [row(4), row(8)])
    store.add_points(d, [row(4, success_rate=0.75)])
    follow = client.follow(exp["id"], poll_s=0.05)
    first = [next(follow) for _ in range(3)]
    assert [(x["run"], x["episode"]) for x in first] == [(a, 4), (a, 8), (d, 4)]
    assert first[2]["success_rate"] == 0.75 and first[2]["seed"] == 1 and "seq" not in first[2]
    arm = {r["id"]: r["arm"] for r in exp["runs"]}
    assert first[0]["arm"] == arm[a] and arm[a] != arm[d]
    # t0 before the timer starts: the point cannot be stored sooner than 0.3 s after it,
    # however long this thread waits between the two lines.
    t0 = time.monotonic()
    later = threading.Timer(0.3, lambda: store.add_points(a, [row(12)]))
    later.start()
    assert (next(follow)["run"], time.monotonic() - t0 >= 0.25) == (a, True)  # as it arrives
    assert client.stop(exp["id"])["changed"] is True
    assert list(follow) == [], "every run ended, every point given: the generator ends"
    frame = client.experiment_frame(exp["id"])
    assert list(frame.columns[:4]) == ["run", "arm", "seed", "episode"]
    assert frame[["run", "episode"]].values.tolist() == [[a, 4], [a, 8], [a, 12], [d, 4]]
    assert frame["config.beta"].tolist() == [0.2, 0.2, 0.2, 0.8]
    assert frame["success_rate"].tolist() == [0.04, 0.08, 0.12, 0.75]
    store.close()
    client.close()


@pytest.mark.timeout(60)
def test_follow_and_a_paged_read_across_a_retry_say_or_keep_one_attempt(api):
    """A run retried while followed starts its episodes again: `follow` gives the new
    attempt's rows after the old ones, each with its `attempt`. A read page by page that
    a retry interrupts starts over, so it holds one attempt's rows, not two of an
    episode."""
    client = macb.Client(api.url, token="s3cret")
    exp = client.start({**TINY, "seeds": [0]})
    run = exp["runs"][0]["id"]
    assign = Assignment(learner="L", actors=("A",), counter="C", evaluator="E")
    store = Store(api.settings.db_path)  # a second connection, as the scheduler has

    def retry(attempt: int, rows: list[dict]) -> None:
        store.finish(run, "failed", "learner died")
        assert client.api.retry_experiment(exp["id"])["retried"] == [run]
        assert store.claim(run, assign)
        assert store.add_points(run, rows, attempt=attempt) == len(rows)

    assert store.claim(run, assign)
    store.add_points(run, [row(4), row(8)], attempt=1)
    follow = client.follow(exp["id"], poll_s=0.05)
    assert [(x["episode"], x["attempt"]) for x in (next(follow), next(follow))] == [
        (4, 1),
        (8, 1),
    ]
    retry(2, [row(4, success_rate=0.5), row(8), row(12)])
    again = [next(follow) for _ in range(3)]
    assert [(x["episode"], x["attempt"]) for x in again] == [(4, 2), (8, 2), (12, 2)]
    assert again[0]["success_rate"] == 0.5

    pages = client.api.metrics
    calls = []

    def metrics(run_id: str, since: int = 0, limit: int | None = None) -> dict:
        calls.append(since)
        if len(calls) == 2:  # between the first page and the second
            retry(3, [row(4, success_rate=0.25)])
        return pages(run_id, since, limit)

    client.api.metrics = metrics  # type: ignore[method-assign]
    got = client.api.all_points(run, page=1)
    assert [(p["episode"], p["success_rate"]) for p in got] == [(4, 0.25)], "attempt 3's only"
    assert calls == [0, 3, 0], "read again from the start once the attempt changed"
    client.api.metrics = pages  # type: ignore[method-assign]
    assert client.stop(exp["id"])["changed"] is True
    assert [(x["episode"], x["attempt"]) for x in follow] == [(4, 3)]
    store.close()
    client.close()


@pytest.mark.timeout(60)
def test_the_docs_api_example_runs_against_the_api(api, capsys):
    (block,) = [b for b in _code_blocks(ROOT / "docs" / "python.md") if "macb.Client" in b]
    done = threading.Event()

    def evaluator() -> None:
        """Points for the experiment the example starts, as its runs would store them."""
        store = Store(api.settings.db_path)
        try:
            while not done.is_set():
                exps = store.experiments()
                runs = store.runs_of([exps[0]["id"]]).get(exps[0]["id"]) if exps else None
                if runs:  # the experiment's row can be there a moment before its runs'
                    for r in runs:
                        store.add_points(r["id"], [row(e) for e in range(10, 201, 10)])
                    return
                time.sleep(0.05)
        finally:
            store.close()

    thread = threading.Thread(target=evaluator)
    thread.start()
    scope: dict = {"macb": macb}
    try:
        exec(block.replace("http://127.0.0.1:8000", api.url), scope)  # noqa: S102
    finally:
        done.set()
        thread.join()
    printed = capsys.readouterr().out.splitlines()
    # Whichever run's points the poll met first may reach episode 100 first: the evaluator
    # stores run 0's points, then run 1's, and a poll can fall between the two.
    ids = [r["id"] for r in scope["exp"]["runs"]]
    lines = [line.split() for line in printed if line.split()[:1] and line.split()[0] in ids]
    by_run: dict[str, list[list[str]]] = {}
    for rid, *point in lines:
        by_run.setdefault(rid, []).append(point)
    stored = [[str(e), str(row(e)["success_rate"])] for e in range(10, 201, 10)]
    assert lines and lines[-1][1:] == ["100", "1.0"], printed
    assert by_run[lines[-1][0]] == stored[:10], printed  # the breaking run: each point, in order
    assert all(pts == stored[: len(pts)] for pts in by_run.values()), printed
    # The example's frame was read right after its break: the evaluator may not have
    # stored the other run's points yet (each run's are one transaction: all or none).
    every = list(range(10, 201, 10))
    live = scope["live"].groupby("run")["episode"].apply(list).to_dict()
    assert live[lines[-1][0]] == every and all(eps == every for eps in live.values()), live
    with macb.Client(api.url, token="s3cret") as client:  # once every point is stored
        frame = client.experiment_frame(scope["exp"]["id"])
    assert sorted(frame["run"].unique()) == sorted(ids) and len(frame) == 40
    assert all(frame[frame["run"] == r]["episode"].tolist() == every for r in ids)
