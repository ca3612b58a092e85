"""A reproduced figure's page: FIGURE.md (what ran, the definitions, each arm beside
the thesis, a verdict per claim, each counting arm against its control), FIGURE.csv.gz
(every point the curves read) and FIGURE-claims.json (for `macb results`), with
FIGURE.png from cli/reproduce/plot.py.
"""

from __future__ import annotations

import csv
import json
import math
import time
from collections import Counter
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from cli.reproduce.analysis import (
    BANDS,
    CONVERGED,
    CSV_COLUMNS,
    LEARNED,
    NOT_REPRODUCED,
    PLATEAU_SHARE,
    REPRODUCED,
    SMOOTH_SHARE,
    Analysis,
    ArmCurve,
    Columns,
    as_columns,
    claim_verdicts,
    count1,
)
from cli.reproduce.controls import claim_per_seed, control_verdicts, summary, why_section
from cli.reproduce.experiments import arm_configs, split_base
from cli.reproduce.plot import thesis_marks, write_png
from cli.reproduce.status import from_points, page_line
from cli.results import claims_record


def _fmt_point(point: dict[str, Any]) -> str:
    return ", ".join(f"{k}={json.dumps(v)}" for k, v in point.items()) or "(the base)"


def _band_text(band: str) -> str:
    if band == "std":  # the pages before the thesis's band was drawn say it so
        return (
            "band: mean +- one standard deviation over seeds (the thesis also draws a 75% "
            "confidence interval, not drawn here)."
        )
    return f"band: {BANDS[band]}, the band the thesis draws (§6 l.373, with seaborn: l.525)."


def _milestone(arm: ArmCurve, episode: int, metric: str) -> str:
    v, at = arm.value_at(episode, metric)
    if v is None or arm.length < episode:
        return "-" if v is None else f"({v:.0%} at {at:,})"
    return f"{v:.0%}"


def started_runs(a: Analysis) -> set[str]:
    """The runs with a row."""
    return {r for r, cols in a.points.items() if len(cols.get("episode", ()))}


def not_started(a: Analysis) -> list[str]:
    """The selected arms none of whose runs has a row yet, while others have: a campaign
    that runs its arms in turns (figure 8's sparse arms, then its dense ones). An arm
    some of whose seeds started is started (its length is the least they reached)."""
    has = started_runs(a)
    arms = [(n, arm) for n, arm in a.arms.items() if arm.runs]
    waiting = [n for n, arm in arms if not has.intersection(arm.runs)]
    return waiting if len(waiting) < len(arms) else []


def started_arms(a: Analysis) -> list[ArmCurve]:
    """The selected arms that have started: every selected arm while none has."""
    waiting = not_started(a)
    return [arm for name, arm in a.arms.items() if arm.runs and name not in waiting]


def _of_each_start(runs: list[dict[str, Any]], field: str, kind: type) -> list[list[Any]]:
    """Per run that lists it, `field`'s value for each start (`start_cpus`,
    `start_codes`), in order, keeping only entries of `kind`."""
    return [
        [v for v in r[field] if isinstance(v, kind)] for r in runs if isinstance(r.get(field), list)
    ]


def what_ran(runs: list[dict[str, Any]], started: set[str] | None = None) -> str:
    """The report's line on what the runs ran on, from each run's provenance (the
    learner's report, `live.provenance`): the precision as run, which may not be the one
    asked (bf16 on a CPU without it runs fp32), the CPUs (of every start, where
    `start_cpus` lists them: a campaign resumed on another kind of machine rounds
    differently from there on) and the code (of every start, where `start_codes` lists
    them). A run outside `started` (the ids with rows, when given) has not run yet, so
    has nothing to report."""
    # provenance.reported(r), read here without it: shared.persist.provenance loads torch.
    starts = [(r.get("live") or {}).get("provenance") for r in runs]
    known = [s for s in starts if isinstance(s, dict)]
    if not known:
        return "- What ran: no run reported its provenance (docs/reliability.md)."
    ran = Counter(str((s.get("learner") or {}).get("precision")) for s in known)
    asked = sorted({str((s.get("learner") or {}).get("precision_asked")) for s in known})
    latest = {c for s in known if isinstance(c := (s.get("machine") or {}).get("cpu"), str)}
    every = _of_each_start(runs, "start_cpus", str)  # each start's CPU, in order
    cpus = sorted({*latest, *(c for cs in every for c in cs)}) or ["unknown"]
    moved = [cs for cs in every if len(set(cs)) > 1]
    firsts = sorted({cs[0] for cs in moved})
    # each start's code: a campaign restarted on a newer checkout names both
    start_codes = [{_commit(c) for c in cs} for cs in _of_each_start(runs, "start_codes", dict)]
    latest_codes = {_commit(s.get("code") or {}) for s in known}
    commits = sorted(latest_codes.union(*start_codes))
    precision = ", ".join(f"{p} on {n} run(s)" for p, n in sorted(ran.items()))
    line = f"- What ran (each run's provenance): learner precision {precision}"
    if set(ran) != set(asked):
        line += f" (**asked {', '.join(asked)}**: a CPU without native bf16 runs fp32)"
    line += f"; CPU {', '.join(cpus)}"
    if moved:
        line += (
            f" ({len(moved)} run(s) started on {' or '.join(firsts)} and resumed on another "
            "CPU: each row is rounded as the CPU of the start that computed it rounds, and "
            "the Restarts line names each restart's CPU)"
        )
    line += f"; code {', '.join(commits)}"
    if changed := sum(1 for cs in start_codes if len(cs) > 1):
        line += (
            f" ({changed} run(s) resumed on other code than they started with: the "
            "Restarts line names each restart's)"
        )
    silent = [r for r, s in zip(runs, starts, strict=True) if not isinstance(s, dict)]
    waiting = 0 if started is None else sum(1 for r in silent if r.get("id") not in started)
    if missing := len(silent) - waiting:
        line += f"; {missing} run(s) reported none"
    if waiting:
        line += f"; {waiting} run(s) not started"
    return line + "."


def _commit(code: dict[str, Any]) -> str:
    """A provenance's code as the report names it: the commit's first 12 digits, and
    whether tracked files differed from it."""
    commit = code.get("commit")
    if not commit:
        return "not a git checkout"
    return f"{str(commit)[:12]}{' (dirty)' if code.get('dirty') else ''}"


def measured(a: Analysis, name: str, config: dict[str, Any]) -> str:
    """The arms table's "measured" cell for arm `name` (its run config `config`): a
    curve's plateau and convergence (collisions: the final count), a table figure's
    success and count-1 % at its length."""
    fig, arm = a.fig, a.arm(name)
    if fig.kind != "table":
        return arm.describe() if fig.metric != "collisions_cum" else summary(a, arm)
    v, _ = arm.value_at(fig.episodes)
    c1 = count1(a, name, config)
    text = "-" if v is None else f"{v:.0%}, " + ("-" if c1 is None else f"{c1:.0f}%")
    if v is not None and arm.length < fig.episodes:
        text += f" (at {arm.length:,})"
    return text


def markdown(a: Analysis, profile: str, out_png: str = "", command: str | None = None) -> str:
    """FIGURE.md: what ran, the definitions, each arm beside what the thesis reports for
    it, a verdict per claim, and each MACB arm against its control."""
    fig, exp = a.fig, a.experiment
    configs = arm_configs(fig)
    base, sets = split_base(configs)
    runs = exp.get("runs") or []
    if runs and "config" in runs[0]:  # what ran: --episodes cuts the files' length
        base["episodes"] = runs[0]["config"]["episodes"]
    base["profile"] = profile
    counts = ", ".join(f"{v} {k}" for k, v in (exp.get("counts") or {}).items())
    waiting = not_started(a)
    begun = started_arms(a)
    lengths = {arm.length for arm in begun}
    window = sorted({arm.window for arm in begun} or {arm.window for arm in a.arms.values()})
    lines = [
        f"# {fig.title}",
        "",
        f"Reproduced with `{command or f'macb reproduce {fig.name} --profile {profile}'}` on "
        f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC. The thesis: {fig.section} of "
        "`count-based-exploration-for-multi-agent-learning.txt`.",
        "",
        f"- Experiment: `{exp.get('id', '?')}` ({exp.get('name', '')}), status "
        f"{exp.get('status', '?')} ({counts or 'no runs'}).",
        f"- Profile `{profile}`; seeds {exp.get('seeds', [])}; the thesis ran 3 seeds of "
        f"{fig.episodes:,} episodes; these runs reached "
        f"{', '.join(f'{n:,}' for n in sorted(lengths)) or 'no'} episodes"
        + (f" ({len(waiting)} arm(s) not started)." if waiting else "."),
        page_line(from_points(exp, a.points, fig.episodes), time.time()),
        *restarts(runs),
        f"- Base config (every arm): {_fmt_point(base)}.",
        f"- Smoothing: centred moving average over {SMOOTH_SHARE:.0%} of each seed's "
        f"evaluation points (W = {', '.join(map(str, window))} point(s); the window shrinks "
        "symmetrically at the ends, which go unsmoothed; cumulative collisions are not "
        f"smoothed), then the mean over seeds; {_band_text(fig.band)}",
        f"- Plateau: the mean over seeds and over the last {PLATEAU_SHARE:.0%} of the "
        f"points. Episodes to convergence: the first episode where the smoothed mean "
        f"reaches {CONVERGED:.0%} of the plateau, if the plateau is at least {LEARNED:.0%} "
        "(else: no plateau). The value at episode E: the mean over seeds and over the W "
        "points up to E (collisions: the count at E); final: the value at the last "
        "episode run.",
        "- Verdicts: reproduced / not reproduced by the stated rule; not run to that "
        "length when a run stopped short of the episodes the claim is about (the measured "
        "number is still given)."
        + (
            " In the plot a hollow diamond marks each value a claim states at an episode, "
            "its bar the range the verdict accepts."
            if thesis_marks(a)
            else ""
        ),
    ]
    stopped = sorted(
        f"{arm.name} seed {seed} at {e:,}"
        for arm in a.arms.values()
        for seed, e in arm.stopped.items()
    )
    if stopped:
        lines += [
            "- Early stopping (`early_stop`, beyond the thesis): "
            f"{len(stopped)} run(s) ended by their rule, finished, not cut short ("
            + "; ".join(stopped)
            + "): a claim beyond where they ended is judged on the episodes they ran, "
            "and says so."
        ]
    lines += [what_ran(runs, started_runs(a))]
    if exp.get("wall_s"):  # local runs: their own clocks, over every start
        lines += [
            f"- Wall time: {exp['wall_s'] / 3600:.2f} h, the longest run's own clock (its "
            "`wall_s`, summed over its starts; runs of a group share it)."
        ]
    if fig.note:
        lines += [f"- {fig.note}"]
    if out_png:
        lines += ["", f"![{fig.name}]({out_png})"]
    lines += ["", "## Arms", ""]
    milestone_cols = [f"{fig.metric} at {e:,}" for e in fig.milestones]
    head = ["arm", "sets over the base", "seeds", "the thesis", "measured", *milestone_cols]
    if fig.kind == "table":
        head = ["arm", "sets over the base", "seeds", "the thesis (sr, c-1)", "measured (sr, c-1)"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for arm_def in fig.arms:
        arm = a.arm(arm_def.name)
        thesis = arm_def.thesis or "not in the thesis (control)"
        row = [
            arm_def.name,
            _fmt_point(sets[arm_def.name]),
            str(len(arm.runs)),
            thesis,
            measured(a, arm_def.name, configs[arm_def.name]),
            *(_milestone(arm, e, fig.metric) for e in fig.milestones),
        ]
        lines.append("| " + " | ".join(row) + " |")
    lines += [
        "",
        "## Claims",
        "",
        "| # | the thesis says | where | the thesis | measured (mean over seeds) | per seed "
        "| verdict |",
    ]
    lines.append("|---|---|---|---|---|---|---|")
    verdicts = claim_verdicts(a)
    for i, (claim, text, verdict) in enumerate(verdicts, 1):
        seeds = claim_per_seed(a, claim.check)
        lines.append(
            f"| {i} | {claim.text} | {claim.where} | {claim.thesis} | {text} | {seeds} "
            f"| **{verdict}** |"
        )
    tally = {v: sum(1 for *_, x in verdicts if x == v) for v in (REPRODUCED, NOT_REPRODUCED)}
    too_short = len(verdicts) - sum(tally.values())
    lines += [
        "",
        f"{tally[REPRODUCED]} reproduced, {tally[NOT_REPRODUCED]} not reproduced, "
        f"{too_short} not run to that length.",
        *why_section(a),
        "",
        "## Against the control",
        "",
        "The control is the constant bonus with the same beta and reward, no counting: a "
        "count-bonus arm that does not beat it owes its effect to the reward shift, not "
        "to counting. The verdict is the Why table's rule: beats the control when their "
        "spreads are apart on the better side ("
        + ("fewer collisions" if fig.metric == "collisions_cum" else "higher")
        + "), at the end or else over the whole run (each seed's mean over the episodes "
        "both ran: an arm that learns sooner), does not beat it when apart on the other, "
        "not distinguishable while they overlap; the measured columns give each arm's "
        "convergence and final value.",
        "",
        "| MACB arm | control | MACB measured | control measured | verdict |",
        "|---|---|---|---|---|",
    ]
    for name, control, mine, theirs, verdict in control_verdicts(a):
        lines.append(f"| {name} | {control or '-'} | {mine} | {theirs} | **{verdict}** |")
    return "\n".join(lines) + "\n"


RESTART_GAP_S = 600.0  # restarts begun this close in time are one restart of the campaign


def restarts(runs: list[dict[str, Any]]) -> list[str]:
    """The header's line on a campaign's restarts, from each run's resumes (`resumes`:
    the starts after its first in its provenance.json, as `cli.local.local_experiment`
    reads them; no line where no run has a provenance.json, or for a cluster's runs,
    which carry none). The starts one command made (their `command`: a `--local` with
    more groups than `--jobs` starts its later groups hours after its first) are one
    restart, and so are restarts begun within RESTART_GAP_S of each other: a command
    that was stopped and given again at once, or starts written before they named their
    command (a command resumes its groups together, each at its cut)."""
    lists = [r["resumes"] for r in runs if isinstance(r.get("resumes"), list)]
    if not lists:
        return []
    every = [x for xs in lists for x in xs]
    if not every:
        return ["- Restarts: none (each run trained in one start)."]
    units: dict[str, list[dict[str, Any]]] = {}
    for i, x in enumerate(every):
        command = x.get("command")
        units.setdefault(f"c:{command}" if isinstance(command, str) else f"s:{i}", []).append(x)
    ordered = sorted(units.values(), key=lambda xs: min(str(x.get("started") or "") for x in xs))
    clusters: list[list[dict[str, Any]]] = []
    last: datetime | None = None
    for these in ordered:
        at = _when(min(str(x.get("started") or "") for x in these))
        if (
            not clusters
            or at is None
            or last is None
            or (at - last).total_seconds() > RESTART_GAP_S
        ):
            clusters.append([])
        clusters[-1].extend(these)
        last = at or last
    parts, unknown = [], False
    for these in clusters:
        eps = sorted({e for x in these if isinstance(e := x.get("episode"), int)})
        missing = any(not isinstance(x.get("episode"), int) for x in these)
        unknown |= missing
        where = " and ".join([*(f"{e:,}" for e in eps), *["?"] * missing])
        commits = sorted({_commit(x.get("code") or {}) for x in these})
        cpus = sorted({str(c) for x in these if (c := x.get("cpu"))})
        on = f", CPU {', '.join(cpus)}" if cpus else ""
        when = min((str(x.get("started") or "") for x in these), default="")
        parts.append(f"{where} (code {', '.join(commits)}{on}{', ' + when if when else ''})")
    note = "; ?: a resume written before its episode was recorded" if unknown else ""
    n = len(clusters)
    times = f"{n} time{'s' * (n != 1)}"
    return [f"- Restarts: resumed {times} (at episodes {'; '.join(parts)}){note}."]


def _when(text: str) -> datetime | None:
    try:
        return datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        return None


def write_csv(exp: dict[str, Any], points: Mapping[str, Columns | list], path: Path) -> Path:
    """FIGURE.csv.gz: every point of every run, only the columns the report reads,
    gzipped with no time in its header, so the same points give the same bytes and a
    page rebuilt at every stop of a campaign commits only what changed. An older page's
    plain FIGURE.csv in the same folder is removed: one file of points per page
    (`cli.results.points_file` still reads either)."""
    import gzip
    import io

    path.with_suffix("").unlink(missing_ok=True)  # FIGURE.csv
    with (
        path.open("wb") as raw,
        gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0) as zipped,
        io.TextIOWrapper(zipped, newline="", encoding="utf-8") as f,
    ):
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for r in exp["runs"]:
            c = as_columns(points.get(r["id"], []))
            fields = [c[k] for k in CSV_COLUMNS[3:]]
            for i in range(len(c["episode"])):
                w.writerow([r["arm"], r["seed"], r["id"], *(_cell(x[i]) for x in fields)])
    return path


def _cell(x: Any) -> Any:
    """A CSV cell: integral values without '.0', a missing value empty."""
    x = float(x)
    if math.isnan(x):
        return ""
    return int(x) if x.is_integer() else x


def write_report(
    a: Analysis,
    points: Mapping[str, Columns | list],
    profile: str,
    out: Path,
    command: str | None = None,
) -> list[Path]:
    """FIGURE.png, FIGURE.md, FIGURE.csv.gz and FIGURE-claims.json (for `macb results`) in
    out/."""
    out.mkdir(parents=True, exist_ok=True)
    name = a.fig.name
    png = write_png(a, profile, out / f"{name}.png")
    md = out / f"{name}.md"
    md.write_text(markdown(a, profile, png.name, command))
    lengths = [arm.length for arm in started_arms(a)]
    record = claims_record(
        name, profile, claim_verdicts(a), min(lengths, default=0), a.fig.episodes,
        list(a.experiment.get("seeds") or []), not_started(a),  # a campaign's next turn
    )  # fmt: skip
    claims = out / f"{name}-claims.json"
    claims.write_text(json.dumps(record, indent=1) + "\n")
    return [png, md, write_csv(a.experiment, points, out / f"{name}.csv.gz"), claims]
