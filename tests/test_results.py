"""`macb results`: docs/results/README.md's claims table is what the figure pages say."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cli.reproduce.figures import FIGURES
from cli.results import BEGIN, END, render, table
from tests.harness import macb as macb_cli

FIG3 = FIGURES["fig3"]


def _page(root: Path, name: str, profile: str, reached: int, verdict: str) -> Path:
    folder = root / name
    folder.mkdir(parents=True)
    claims = [{"text": c.text, "measured": f"measured {i}", "verdict": verdict}
              for i, c in enumerate(FIG3.claims)]  # fmt: skip
    record = {"format": 1, "figure": "fig3", "profile": profile, "episodes_reached": reached,
              "episodes_full": 5000, "seeds": [0, 1, 2], "claims": claims}  # fmt: skip
    path = folder / "fig3-claims.json"
    path.write_text(json.dumps(record))
    return path


def _results(tmp_path: Path) -> Path:
    root = tmp_path / "results"
    root.mkdir()
    (root / "README.md").write_text(f"# Results\n\nprose\n\n{BEGIN}\nold\n{END}\n\nafter\n")
    return root


def test_each_claim_shows_each_profiles_page_and_claims_without_one_say_not_run(tmp_path):
    root = _results(tmp_path)
    _page(root, "fig3-mpe2", "mpe2", 5000, "reproduced")
    _page(root, "fig3-thesis", "thesis", 1200, "not run to that length")
    text = table(root)
    assert "| [fig3-mpe2](fig3-mpe2/fig3.md) | fig3 | mpe2 | full length, 3 seeds | none |" in text
    assert "| fig3 | thesis | 1,200 of 5,000 episodes, 3 seeds |" in text
    rows = [line for line in text.splitlines() if line.startswith("| fig3 | ")]
    assert len(rows) == len(FIG3.claims)
    for i, row in enumerate(rows):
        assert f"| measured {i} | measured {i} | not run to that length; reproduced |" in row
    others = [line for line in text.splitlines() if line.startswith("| fig8 | ")]
    assert len(others) == len(FIGURES["fig8"].claims)
    assert all(row.endswith("| not run | not run | not run; not run |") for row in others)


def test_a_page_whose_campaign_has_arms_not_started_says_how_many(tmp_path):
    root = _results(tmp_path)
    path = _page(root, "fig3-thesis", "thesis", 1200, "not run to that length")
    record = json.loads(path.read_text())
    path.write_text(json.dumps({**record, "arms_not_started": ["beta=1.2", "beta=0.6"]}))
    assert "| 1,200 of 5,000 episodes (2 arm(s) not started), 3 seeds |" in table(root)
    path.write_text(json.dumps({**record, "episodes_reached": 5000, "arms_not_started": ["x"]}))
    assert "| the started arms at full length (1 arm(s) not started), 3 seeds |" in table(root)


def test_the_readme_keeps_its_prose_and_check_says_when_it_is_stale(tmp_path):
    root = _results(tmp_path)
    _page(root, "fig3-mpe2", "mpe2", 5000, "reproduced")
    stale = macb_cli("results", "--dir", str(root), "--check")
    assert stale.returncode == 1 and "is not what its pages say" in stale.stderr
    wrote = macb_cli("results", "--dir", str(root))
    assert wrote.returncode == 0, wrote.stderr
    readme = (root / "README.md").read_text()
    assert readme.startswith("# Results\n\nprose\n\n") and readme.endswith(f"{END}\n\nafter\n")
    assert "old" not in readme and readme == render(readme, table(root))
    assert macb_cli("results", "--dir", str(root), "--check").returncode == 0


@pytest.mark.parametrize("content", ["{not json", '{"format": 1, "figure": "fig99"}'])
def test_a_bad_claims_file_is_refused_naming_it(tmp_path, content):
    root = _results(tmp_path)
    path = _page(root, "fig3-mpe2", "mpe2", 5000, "reproduced")
    path.write_text(content)
    for check in ([], ["--check"]):  # 2, unreadable: not 1, a stale README
        got = macb_cli("results", "--dir", str(root), *check)
        assert got.returncode == 2 and str(path) in got.stderr, got.stderr
        assert "not a claims file" in got.stderr and "Traceback" not in got.stderr
    assert "old" in (root / "README.md").read_text()  # nothing written


@pytest.mark.parametrize(
    "damage",
    [
        {"episodes_reached": None},
        {"episodes_reached": "400"},
        {"seeds": 3},
        {"claims": ["a claim"]},
        {"claims": [{"measured": "x", "verdict": "y"}]},
    ],
)
def test_a_claims_file_missing_or_mistyping_a_field_the_readme_reads_is_refused(tmp_path, damage):
    """Every field the README's rows read is checked when the file is read: a damaged
    one is refused naming the file (exit 2), not a KeyError or TypeError later (exit 1,
    which --check means as "stale")."""
    root = _results(tmp_path)
    path = _page(root, "fig3-mpe2", "mpe2", 5000, "reproduced")
    record = json.loads(path.read_text())
    record.update(damage)
    path.write_text(json.dumps({k: v for k, v in record.items() if v is not None}))
    for check in ([], ["--check"]):
        got = macb_cli("results", "--dir", str(root), *check)
        assert got.returncode == 2 and str(path) in got.stderr, got.stderr
        assert "not a claims file" in got.stderr and "Traceback" not in got.stderr


def test_compare_refuses_a_points_row_without_run_or_episode_naming_the_file(tmp_path):
    import gzip

    root = _results(tmp_path)
    folder = _page(root, "fig3-mpe2", "mpe2", 5000, "reproduced").parent
    (folder / "fig3.csv.gz").write_bytes(
        gzip.compress(b"arm,seed,run,episode,success_rate\nb,0,b-s0,1,0.5\nb,0,b-s0\n")
    )
    runs = tmp_path / "runs"
    runs.mkdir()
    got = macb_cli("results", "--compare", str(folder), "--runs", str(runs))
    assert got.returncode == 2 and f"{folder / 'fig3.csv.gz'}: line 3" in got.stderr, got.stderr
    assert "Traceback" not in got.stderr


def test_a_torn_points_file_is_refused_naming_it(tmp_path):
    """--compare and macb.load_page on a page whose FIGURE.csv.gz is torn (a copy cut
    short) name the file; --compare exits 2 (cannot read), not 1 (a difference), as it
    does for a folder that is not a page."""
    import gzip

    import macb

    root = _results(tmp_path)
    folder = _page(root, "fig3-mpe2", "mpe2", 5000, "reproduced").parent
    data = gzip.compress(b"arm,seed,run,episode,success_rate\n" + b"b,0,b-s0,1,0.5\n" * 500)
    (folder / "fig3.csv.gz").write_bytes(data[: len(data) // 2])
    runs = tmp_path / "runs"
    runs.mkdir()
    got = macb_cli("results", "--compare", str(folder), "--runs", str(runs))
    assert got.returncode == 2 and str(folder / "fig3.csv.gz") in got.stderr, got.stderr
    assert "Traceback" not in got.stderr
    with pytest.raises(macb.RunsError, match="fig3.csv.gz: not a page's points"):
        macb.load_page(folder)
    none = macb_cli("results", "--compare", str(tmp_path), "--runs", str(runs))
    assert none.returncode == 2 and "should hold one page's points" in none.stderr


def test_the_repositorys_results_readme_is_what_its_pages_say():
    got = macb_cli("results", "--check")
    assert got.returncode == 0, got.stderr


def test_a_page_s_points_are_its_csv_gz_and_an_older_page_s_plain_csv_still_reads(tmp_path):
    """A page writes FIGURE.csv.gz; a page written before holds FIGURE.csv: both are
    linked from the table and read by macb.load_page, gzipped first; --check sees a
    page whose points moved from one to the other."""
    import gzip

    import macb
    from cli.results import points_file, read_points

    root = _results(tmp_path)
    folder = _page(root, "fig3-mpe2", "mpe2", 5000, "reproduced").parent
    text = "arm,seed,run,episode,success_rate\nbeta=0.0,0,b-s0,10,0.5\nbeta=0.0,0,b-s0,20,\n"
    (folder / "fig3.csv").write_text(text)
    assert points_file(folder, "fig3") == folder / "fig3.csv"
    assert "| full length, 3 seeds | [fig3.csv](fig3-mpe2/fig3.csv) |" in table(root)
    assert macb_cli("results", "--dir", str(root)).returncode == 0
    old = macb.load_page(folder)
    assert list(old["episode"]) == [10, 20] and old["success_rate"].isna().tolist() == [0, 1]
    (folder / "fig3.csv.gz").write_bytes(gzip.compress(text.replace("0.5", "0.25").encode()))
    assert points_file(folder, "fig3") == folder / "fig3.csv.gz"
    assert read_points(folder / "fig3.csv.gz")[0]["success_rate"] == "0.25"
    assert macb.load_page(folder)["success_rate"][0] == 0.25
    assert macb.load_page(folder / "fig3.csv")["success_rate"][0] == 0.5
    stale = macb_cli("results", "--dir", str(root), "--check")
    assert stale.returncode == 1, "the table links the page's .csv.gz now"
    with pytest.raises(macb.RunsError, match="no page's points"):
        macb.load_page(tmp_path)
    copied = tmp_path / "copied"  # the points alone, without their claims file
    copied.mkdir()
    (copied / "fig3.csv.gz").write_bytes((folder / "fig3.csv.gz").read_bytes())
    assert macb.load_page(copied)["success_rate"][0] == 0.25
    (copied / "fig8.csv.gz").write_bytes((folder / "fig3.csv.gz").read_bytes())
    with pytest.raises(macb.RunsError, match="which page's points"):
        macb.load_page(copied)
    text = tmp_path / "notes.txt"  # a file that parses as a CSV of one column
    text.write_text("hi\n")
    with pytest.raises(macb.RunsError, match=r"notes.txt: not a page's points \(no run or"):
        macb.load_page(text)
    with pytest.raises(macb.RunsError, match="nowhere: no such page"):
        macb.load_page(tmp_path / "nowhere")


def _train(out: Path, seed: int) -> None:
    """A real run of a few episodes, as `macb train` writes it (distance reward: its
    evaluation returns differ from seed to seed from the first point)."""
    done = macb_cli("train", "--task", "speaker_listener", "--algo", "cen-maddpg", "--explore",
                    "cen-macb", "--hidden", "16,16", "--batch-size", "8", "--learning-starts",
                    "20", "--eval-every", "2", "--eval-episodes", "1", "--learner-lanes", "1",
                    "--reward", "dense", "--episodes", "8", "--seed", str(seed), "--out",
                    str(out), "--quiet")  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]


def test_compare_says_whether_runs_give_a_page_s_points_bit_for_bit(tmp_path):
    from cli.local import run_rows
    from cli.reproduce.render import write_csv

    first, again, other = (tmp_path / n / "arm-s0" for n in ("first", "again", "other"))
    _train(first, seed=0)
    _train(again, seed=0)
    _train(other, seed=1)
    page = tmp_path / "page"
    page.mkdir()
    exp = {"runs": [{"id": "arm-s0", "arm": "arm", "seed": 0}]}
    write_csv(exp, {"arm-s0": run_rows(first)}, page / "fig8.csv.gz")
    episodes = len(run_rows(first))
    assert episodes >= 4

    same = macb_cli("results", "--compare", str(page), "--runs", str(again.parent))
    assert same.returncode == 0, same.stdout + same.stderr
    assert f"arm-s0: equal at all {episodes} episodes both have" in same.stdout

    differ = macb_cli("results", "--compare", str(page), "--runs", str(other.parent))
    assert differ.returncode == 1, differ.stdout + differ.stderr
    assert "arm-s0:" in differ.stdout and "differ; first at episode" in differ.stdout
    assert "on the page" in differ.stdout and "1 differ" in differ.stdout
    # The page's run on this machine's CPU too: a difference, not named as rounding's.
    here = json.loads((first / "provenance.json").read_text())["starts"][0]["machine"]["cpu"]
    record = page / "fig8-runs.json"
    record.write_text(json.dumps({"runs": [{"id": "arm-s0", "start_cpus": [here]}]}))
    same_cpu = macb_cli("results", "--compare", str(page), "--runs", str(other.parent))
    assert same_cpu.returncode == 1 and "another CPU" not in same_cpu.stdout, same_cpu.stdout
    # On another kind of CPU (every start's, or an older page's latest provenance alone):
    # the runs that differ are named, and rounding as what may explain it.
    for run in (
        {"id": "arm-s0", "start_cpus": ["Some Other CPU"]},
        {"id": "arm-s0", "provenance": {"machine": {"cpu": "Some Other CPU"}}},
    ):
        record.write_text(json.dumps({"runs": [run]}))
        crossed = macb_cli("results", "--compare", str(page), "--runs", str(other.parent))
        assert crossed.returncode == 1, crossed.stdout + crossed.stderr
        assert (
            "1 of the 1 that differ ran on another CPU than the page's (Some Other CPU on the "
            f"page; {here} here): arm-s0. Another kind of CPU rounds"
        ) in crossed.stdout
    # A record it cannot read is no hint, and no crash after the result.
    for bad in ('{"runs": 5}', '{"runs": [{"id": "arm-s0", "provenance": "x"}]}', "not json"):
        record.write_text(bad)
        got = macb_cli("results", "--compare", str(page), "--runs", str(other.parent))
        assert got.returncode == 1 and not got.stderr and "another CPU" not in got.stdout, bad

    missing = macb_cli("results", "--compare", str(page), "--runs", str(tmp_path / "nowhere"))
    assert missing.returncode == 2 and not missing.stdout
    assert f"has a folder in {tmp_path / 'nowhere'}: no such folder" in missing.stderr
    (tmp_path / "a-file").write_text("")
    filed = macb_cli("results", "--compare", str(page), "--runs", str(tmp_path / "a-file"))
    assert filed.returncode == 2 and "a-file: a file, not a folder" in filed.stderr
    outer = macb_cli("results", "--compare", str(page), "--runs", str(tmp_path))  # OUT/runs?
    assert outer.returncode == 2 and "none of the page's 1 run(s) has a folder in" in outer.stderr
    (tmp_path / "runs").mkdir()
    outer = macb_cli("results", "--compare", str(page), "--runs", str(tmp_path))
    assert f"which holds a runs folder: give --runs {tmp_path / 'runs'}" in outer.stderr

    (other / "metrics.jsonl").write_text('{"episode": 1}\nnot json\n{"episode": 3}\n')
    torn = macb_cli("results", "--compare", str(page), "--runs", str(other.parent))
    assert torn.returncode == 2 and "metrics.jsonl, line 2" in torn.stderr

    no_runs = macb_cli("results", "--compare", str(page))
    assert no_runs.returncode == 2 and "--compare needs --runs" in no_runs.stderr
    # --runs alone was ignored, and the index rewritten as if it had not been given.
    runs_alone = macb_cli("results", "--dir", str(tmp_path / "nowhere"), "--runs", str(other))
    assert runs_alone.returncode == 2 and "--runs is for --compare" in runs_alone.stderr
