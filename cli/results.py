"""`macb results`: docs/results/README.md's table of every thesis claim, from the pages.

Each figure's page (`macb reproduce FIGURE`, written by cli/reproduce/render.py) keeps its
verdicts in `FIGURE-claims.json`. This command reads every page under a results folder
and writes one row per page (its length, a link to its points: FIGURE.csv.gz, or an
older page's FIGURE.csv) and one row per claim of cli/reproduce/figures.py (every claim
of the thesis's sections 6.1-6.4): what the thesis reports, what each profile measured
and how long its runs were, and the verdicts; a claim with no page says `not run`. The
README's prose stays as written: only the part between the two markers is generated, so
the table can never disagree with the pages (`--check` fails when it does).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from cli.reproduce.figures import FIGURES, PROFILES

BEGIN = "<!-- results:begin (macb results writes this part) -->"
END = "<!-- results:end -->"
CLAIMS_FORMAT = 1


def claims_record(figure: str, profile: str, verdicts: list, reached: int, full: int,
                  seeds: list[int], not_started: list[str] | None = None,
                  ) -> dict[str, Any]:  # fmt: skip
    """What a page says about its claims, for `macb results`: `reached` is how far the
    arms started got, `not_started` the arms with no row yet."""
    return {
        "format": CLAIMS_FORMAT,
        "figure": figure,
        "profile": profile,
        "episodes_reached": reached,
        "episodes_full": full,
        "seeds": seeds,
        "arms_not_started": list(not_started or []),
        "claims": [
            {"text": c.text, "measured": text, "verdict": verdict} for c, text, verdict in verdicts
        ],
    }


class ResultsError(ValueError):
    """A page or its files that cannot be read: the message names the file and why."""


def read_pages(root: Path) -> dict[tuple[str, str], tuple[Path, dict[str, Any]]]:
    """(figure, profile) -> (its page's claims file, the record) for every page under root.
    A claims file that cannot be read is refused, naming it."""
    pages: dict[tuple[str, str], tuple[Path, dict[str, Any]]] = {}
    for path in sorted(root.glob("*/*-claims.json")):
        try:
            record = json.loads(path.read_text())
            key = (record["figure"], record["profile"])
            if record.get("format") != CLAIMS_FORMAT or key[0] not in FIGURES:
                raise ValueError(f"format {record.get('format')!r}, figure {key[0]!r}")
            if key[1] not in PROFILES or not isinstance(record["claims"], list):
                raise ValueError(f"profile {key[1]!r}")
            _check_record(record)
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise ResultsError(f"{path}: not a claims file ({err})") from None
        if key in pages:
            raise ResultsError(f"{path} and {pages[key][0]} both hold {key}")
        pages[key] = (path, record)
    return pages


def _check_record(record: dict[str, Any]) -> None:
    """ValueError naming the first field a claims record lacks or holds wrongly (the
    README's rows read each of them)."""
    for name in ("episodes_reached", "episodes_full"):
        if not isinstance(record.get(name), int) or isinstance(record.get(name), bool):
            raise ValueError(f"{name}: {record.get(name)!r}, not a whole number")
    if not isinstance(record.get("seeds"), list):
        raise ValueError(f"seeds: {record.get('seeds')!r}, not a list")
    for i, claim in enumerate(record["claims"], 1):
        if not isinstance(claim, dict) or not all(
            isinstance(claim.get(k), str) for k in ("text", "measured", "verdict")
        ):
            raise ValueError(f"claim {i}: not an object of text, measured and verdict strings")


def points_files(folder: Path) -> list[Path]:
    """Every page's points file in `folder`: its FIGURE.csv.gz files, else (an older
    page) its plain FIGURE.csv files."""
    return sorted(folder.glob("*.csv.gz")) or sorted(folder.glob("*.csv"))


def points_file(folder: Path, figure: str) -> Path | None:
    """A page's file of points: FIGURE.csv.gz, or an older page's FIGURE.csv (written
    plain up to 4 MB); None when it has neither."""
    for name in (f"{figure}.csv.gz", f"{figure}.csv"):
        if (folder / name).is_file():
            return folder / name
    return None


def read_points(path: Path) -> list[dict[str, str]]:
    """A page's points as text rows (the CSV's header the keys), gzipped or not;
    ResultsError naming the file when it does not read as that."""
    import csv
    import gzip
    import io
    import zlib

    try:
        raw = path.read_bytes()
        if path.suffix == ".gz":
            raw = gzip.decompress(raw)
        return list(csv.DictReader(io.StringIO(raw.decode("utf-8"), newline="")))
    except (OSError, EOFError, zlib.error, UnicodeDecodeError, csv.Error) as err:
        raise ResultsError(f"{path}: not a page's points ({err})") from err


KEYS = ("arm", "seed", "run", "episode")


def _value(x: Any) -> float | None:
    """A point's value for comparing: a number, or None where it is missing (an empty
    CSV cell, a NaN, a column a row lacks)."""
    if x is None or x == "":
        return None
    v = float(x)
    return None if math.isnan(v) else v


def compare_points(page: Path, runs_dir: Path) -> list[tuple[str, int, int, str | None]]:
    """Each run of a page's points against its folder in runs_dir, episode by episode,
    every column of the points file: (run, episodes both have, how many of those are
    equal in every column, the first difference or why there is nothing to compare).
    Equal means equal floats: the points file keeps each value's full repr, so rows a
    second campaign of the same code on the same kind of CPU gives compare equal.
    A folder's unreadable rows raise `cli.local.MetricsError`, naming the file; a page
    without one points file, or whose points do not read, ResultsError."""
    from cli.local import run_rows

    files = points_files(page)
    if len(files) != 1:
        held = ", ".join(f.name for f in files) or "none"
        raise ResultsError(f"{page} should hold one page's points (FIGURE.csv.gz); "
                           f"it holds {held}")  # fmt: skip
    found = files[0]
    by_run: dict[str, dict[int, dict[str, str]]] = {}
    for line, r in enumerate(read_points(found), 2):
        try:
            by_run.setdefault(r["run"], {})[int(float(r["episode"]))] = r
        except (KeyError, TypeError, ValueError) as err:  # a short row gives None cells
            raise ResultsError(f"{found}: line {line} has no run and episode ({err})") from None
    out: list[tuple[str, int, int, str | None]] = []
    for run, points in by_run.items():
        folder = runs_dir / run
        if not folder.is_dir():
            out.append((run, 0, 0, f"no folder {folder}"))
            continue
        rows = {int(row["episode"]): row for row in run_rows(folder) if "episode" in row}
        both = sorted(set(points) & set(rows))
        first, same = None, 0
        for ep in both:
            try:
                diff = [
                    (c, v, rows[ep].get(c))
                    for c, v in points[ep].items()
                    if c not in KEYS and _value(v) != _value(rows[ep].get(c))
                ]
            except (TypeError, ValueError) as err:  # a cell of neither that is no number
                raise ResultsError(f"{found} or {folder}: episode {ep:,}: {err}") from None
            if not diff:
                same += 1
            elif first is None:
                c, v, w = diff[0]
                first = f"episode {ep:,}: {c} {v} on the page, {w} in the folder"
        if not both:
            first = f"no episode in common ({len(points):,} on the page, {len(rows):,} in {folder})"
        out.append((run, len(both), same, first))
    return out


def _json(path: Path) -> Any:
    """A JSON file's data, or None where it is missing or does not parse (a hint's
    source, never a verdict's)."""
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return None


def page_cpus(page: Path) -> dict[str, set[str]]:
    """Each run's CPUs as the page's FIGURE-runs.json records them: every start's
    (`start_cpus`), or an older page's latest start's; {} without the file, and nothing
    for an entry it cannot read (the record is a hint here, never a verdict)."""
    from cli.local import start_cpu

    out: dict[str, set[str]] = {}
    for points in points_files(page):
        figure = points.name.split(".")[0]
        record = _json(page / f"{figure}-runs.json")
        runs = record.get("runs") if isinstance(record, dict) else None
        for r in runs if isinstance(runs, list) else []:
            if not isinstance(r, dict) or not isinstance(r.get("id"), str):
                continue
            cpus = r.get("start_cpus")
            if not isinstance(cpus, list):
                cpus = [start_cpu(r.get("provenance"))]
            if found := {c for c in cpus if isinstance(c, str)}:
                out[r["id"]] = found
    return out


def folder_cpus(folder: Path) -> set[str]:
    """The CPUs of a run folder's starts, from its provenance.json (empty without it, or
    for entries it cannot read)."""
    from cli.local import start_cpu

    record = _json(folder / "provenance.json")
    starts = record.get("starts") if isinstance(record, dict) else None
    return {c for s in starts if (c := start_cpu(s))} if isinstance(starts, list) else set()


def cmd_compare(page: Path, runs_dir: Path) -> int:
    """`macb results --compare PAGE --runs DIR`: 0 when every run's common points are
    equal, 1 when one differs, 2 when a run has nothing to compare or cannot be read.
    Runs that differ and ran on another CPU than the page's (its FIGURE-runs.json
    against their provenance.json) are named: rounding, not the code, may explain them."""
    from cli.local import MetricsError

    try:
        result = compare_points(page, runs_dir)
    except (MetricsError, ResultsError) as err:
        print(f"macb results: {err}", file=sys.stderr)
        return 2
    if result and not any((runs_dir / run).is_dir() for run, *_ in result):
        hint = "" if runs_dir.is_dir() else ": no such folder"
        if runs_dir.exists() and not runs_dir.is_dir():
            hint = ": a file, not a folder"
        if (runs_dir / "runs").is_dir():  # OUT given for OUT/runs
            hint = f", which holds a runs folder: give --runs {runs_dir / 'runs'}"
        print(
            f"macb results: none of the page's {len(result)} run(s) has a folder in "
            f"{runs_dir}{hint}",
            file=sys.stderr,
        )
        return 2
    for run, both, same, why in result:
        if both and same == both:
            print(f"{run}: equal at all {both:,} episodes both have")
        elif both:
            print(f"{run}: {both - same:,} of {both:,} episodes differ; first at {why}")
        else:
            print(f"{run}: {why}")
    differ = sum(1 for _, both, same, _ in result if same != both)
    empty = sum(1 for _, both, *_ in result if not both)
    least = min((both for _, both, *_ in result if both), default=0)
    print(
        f"{len(result) - differ - empty} of {len(result)} run(s) equal to {page}'s points "
        f"at every episode in common (each at least {least:,}); {differ} differ, "
        f"{empty} with nothing to compare"
    )
    if differ:
        theirs = page_cpus(page)
        crossed = {
            run: (theirs[run], mine)
            for run, both, same, _ in result
            if same != both and theirs.get(run) and (mine := folder_cpus(runs_dir / run))
            and mine != theirs[run]
        }  # fmt: skip
        if crossed:
            was = sorted({c for a, _ in crossed.values() for c in a})
            now = sorted({c for _, b in crossed.values() for c in b})
            print(
                f"{len(crossed)} of the {differ} that differ ran on another CPU than the "
                f"page's ({', '.join(was)} on the page; {', '.join(now)} here): "
                f"{', '.join(sorted(crossed))}. Another kind of CPU rounds the fp32 update "
                "differently, which may explain it: the same code gives the same rows only "
                "on the same kind (docs/reliability.md, 'What a run ran on')"
            )
    return 1 if differ else 2 if empty or not result else 0


def _ours(page: tuple[Path, dict[str, Any]] | None, claim: str, root: Path) -> tuple[str, str]:
    """(the measured cell, the verdict) of one claim on one page."""
    if page is None:
        return "not run", "not run"
    path, record = page
    found = next((c for c in record["claims"] if c["text"] == claim), None)
    if found is None:
        return f"not on [the page]({path.parent.relative_to(root)}/)", "not run"
    return found["measured"], found["verdict"]


def _length(record: dict[str, Any]) -> str:
    reached, full = record["episodes_reached"], record["episodes_full"]
    seeds = len(record["seeds"])
    length = "full length" if reached >= full else f"{reached:,} of {full:,} episodes"
    if waiting := record.get("arms_not_started"):  # absent from older pages' records
        started = "the started arms at " + length if reached >= full else length
        length = f"{started} ({len(waiting)} arm(s) not started)"
    return f"{length}, {seeds} seed{'s' * (seeds != 1)}"


def table(root: Path) -> str:
    """The generated part of the README: the pages, then one row per claim."""
    pages = read_pages(root)
    lines = ["| page | figure | profile | length | points |", "|---|---|---|---|---|"]
    for (figure, profile), (path, record) in sorted(pages.items()):
        link = f"[{path.parent.name}]({path.parent.name}/{figure}.md)"
        found = points_file(path.parent, figure)
        points = f"[{found.name}]({path.parent.name}/{found.name})" if found else "none"
        lines.append(f"| {link} | {figure} | {profile} | {_length(record)} | {points} |")
    if not pages:
        lines.append("| (none yet) | | | | |")
    lines += [
        "",
        "| figure | the thesis says | where | the thesis | ours, profile thesis "
        "| ours, profile mpe2 | verdict (thesis; mpe2) |",
        "|---|---|---|---|---|---|---|",
    ]
    for fig in FIGURES.values():
        for claim in fig.claims:
            cells = [_ours(pages.get((fig.name, p)), claim.text, root) for p in PROFILES]
            by_profile = dict(zip(PROFILES, cells, strict=True))
            verdict = "; ".join(by_profile[p][1] for p in ("thesis", "mpe2"))
            lines.append(
                f"| {fig.name} | {claim.text} | {claim.where} | {claim.thesis} "
                f"| {by_profile['thesis'][0]} | {by_profile['mpe2'][0]} | {verdict} |"
            )
    return "\n".join(lines) + "\n"


def render(readme: str, generated: str) -> str:
    """The README with its generated part replaced (the markers must be there)."""
    if BEGIN not in readme or END not in readme:
        raise ResultsError(f"the README lacks its markers {BEGIN!r} ... {END!r}")
    head, rest = readme.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{BEGIN}\n{generated}{END}{tail}"


def cmd_results(args: argparse.Namespace) -> int:
    """`macb results`: 0 written (or, --check, up to date), 1 stale (--check), 2 a page
    or the README that does not read (named); --compare: cmd_compare's codes."""
    try:
        return _results(args)
    except ResultsError as err:
        print(f"macb results: {err}", file=sys.stderr)
        return 2


def _results(args: argparse.Namespace) -> int:
    if args.compare:
        if not args.runs:
            print("macb results: --compare needs --runs DIR (the runs' folders)", file=sys.stderr)
            return 2
        return cmd_compare(Path(args.compare), Path(args.runs))
    if args.runs:  # (taken and ignored, before: the index was rewritten instead)
        print("macb results: --runs is for --compare", file=sys.stderr)
        return 2
    root = Path(args.dir)
    readme = root / "README.md"
    if not readme.is_file():
        print(f"macb results: no {readme}", file=sys.stderr)
        return 2
    old = readme.read_text()
    new = render(old, table(root))
    if args.check:
        if new != old:
            print(f"macb results: {readme} is not what its pages say; run `macb results "
                  f"--dir {root}`", file=sys.stderr)  # fmt: skip
            return 1
        print(f"{readme}: up to date with its {len(read_pages(root))} page(s)")
        return 0
    readme.write_text(new)
    print(f"wrote {readme} from {len(read_pages(root))} page(s)")
    return 0


def add_results_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "results",
        help="rebuild docs/results/README.md's table of the thesis's claims from the pages",
        description="Read every figure page under DIR (the FIGURE-claims.json that `macb "
        "reproduce` writes beside FIGURE.md) and write the table of every claim of the "
        "thesis, the thesis's number beside each profile's measured one and its verdict, "
        "into DIR/README.md between its markers.",
    )
    p.add_argument("--dir", default="docs/results", help="the results folder")
    p.add_argument(
        "--check", action="store_true", help="write nothing; exit 1 if the README is stale"
    )
    p.add_argument(
        "--compare",
        metavar="PAGE",
        help="write nothing: compare a page's points (PAGE/FIGURE.csv.gz) with the runs' "
        "folders in --runs, episode by episode, every column: do these runs give that "
        "page's rows bit for bit (a second campaign of the same code, a run on another "
        "machine)? Exit 0 equal, 1 a difference (the first named), 2 nothing to compare or "
        "a file that does not read (named)",
    )
    p.add_argument("--runs", metavar="DIR", help="with --compare: the runs' folders (OUT/runs)")
    p.set_defaults(func=cmd_results)
