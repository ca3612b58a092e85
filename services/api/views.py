"""Store rows -> the public shapes (RunPublic, ExperimentPublic) and learning curves."""

from __future__ import annotations

import math
from collections import defaultdict
from datetime import UTC, datetime
from typing import Any

from shared.net.stats import LearnerStats

from .store import Store


def _ts(t: float | None) -> datetime | None:
    return datetime.fromtimestamp(t, UTC) if t else None


def run_public(run: dict[str, Any], stats: tuple[int, int, int]) -> dict[str, Any]:
    points, _, last_episode = stats
    episodes = int(run["config"].get("episodes", 0)) or 1
    learner = LearnerStats.from_wire(run["live"].get("learner") or {})
    return {
        "id": run["id"],
        "experiment_id": run["experiment_id"],
        "index": run["idx"],
        "seed": run["seed"],
        "arm": run["arm"],
        "point": run["point"],
        "config": run["config"],
        "actors": run["actors"],
        "status": run["status"],
        "reason": run["reason"],
        "created": _ts(run["created"]),
        "started": _ts(run["started"]),
        "ended": _ts(run["ended"]),
        "progress": {
            "episode": last_episode,
            "episodes": episodes,
            "fraction": 1.0 if run["status"] == "completed" else min(1.0, last_episode / episodes),
            "trained_episodes": int(learner.episodes_ingested or 0),
        },
        "points": points,
        "attempts": run.get("attempts", 1),
        "assign": run["assign"],
        "services": run["services"],
        "live": run["live"],
    }


def experiment_status(runs: list[dict[str, Any]]) -> str:
    statuses = {r["status"] for r in runs}
    if statuses <= {"queued"}:
        return "queued"
    if statuses & {"queued", "running"}:
        return "running"
    if statuses == {"completed"}:
        return "completed"
    return "failed" if "failed" in statuses else "stopped"


def experiment_public(
    exp: dict[str, Any], runs: list[dict[str, Any]], stats: dict[str, tuple[int, int, int]]
) -> dict[str, Any]:
    spec = exp["spec"]
    counts: dict[str, int] = defaultdict(int)
    for r in runs:
        counts[r["status"]] += 1
    return {
        "id": exp["id"],
        "name": exp["name"],
        "created": _ts(exp["created"]),
        "status": experiment_status(runs),
        "counts": dict(counts),
        "config": spec.get("config", {}),
        "seeds": spec.get("seeds", []),
        "grid": spec.get("grid"),
        "arms": spec.get("arms"),
        "actors": spec.get("actors", 1),
        "runs": [run_public(r, stats[r["id"]]) for r in runs],
    }


def load_experiments(store: Store, exps: list[dict[str, Any]]) -> list[dict[str, Any]]:
    runs = store.runs_of([e["id"] for e in exps])
    stats = store.point_stats([r["id"] for rs in runs.values() for r in rs])
    return [experiment_public(e, runs[e["id"]], stats) for e in exps]


def load_run(store: Store, run_id: str) -> dict[str, Any] | None:
    run = store.run(run_id)
    if run is None:
        return None
    return run_public(run, store.point_stats([run_id])[run_id])


# ---------------------------------------------------------------- curves
# The metrics of the count tables. An arm that counts nothing (explore none or constant)
# has no table, so its rows carry 0 for these: no curve of them is drawn for it.
COUNT_METRICS = ("count1_pct", "sampled_count1_pct", "table_size", "counted_transitions")
COUNTS_NOTHING = ("none", "constant")


def _finite(x: Any) -> float | None:
    if isinstance(x, bool) or not isinstance(x, int | float):
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def curves(store: Store, exp_id: str, metrics: list[str]) -> dict[str, Any] | None:
    """Per metric and arm: mean and mean +- std over the arm's seeds at each episode.

    Runs are grouped by the arm name they carry, in the order of their first run, so a
    figure's arms keep the order they were given in."""
    exp = store.experiment(exp_id)
    if exp is None:
        return None
    runs = store.runs_of([exp_id])[exp_id]
    points = {r["id"]: store.points(r["id"]) for r in runs}
    return curves_of(exp_id, exp["name"], runs, points, metrics)


def curves_of(
    exp_id: str,
    name: str,
    runs: list[dict[str, Any]],
    points: dict[str, list[dict[str, Any]]],
    metrics: list[str],
) -> dict[str, Any]:
    """`curves` of given runs (each with id, arm, point, seed, and its config if known)
    and their points: also what `macb run --local` plots from its runs' folders. An arm
    that counts nothing has empty curves of the `COUNT_METRICS`."""
    groups: dict[str, dict[str, Any]] = {}
    for r in runs:
        g = groups.setdefault(
            r["arm"],
            {
                "name": r["arm"],
                "label": r["arm"],
                "point": r["point"],
                "explore": (r.get("config") or {}).get("explore"),
                "runs": [],
                "seeds": [],
            },
        )
        g["runs"].append(r["id"])
        g["seeds"].append(r["seed"])
    out: dict[str, list[dict[str, Any]]] = {}
    for metric in metrics:
        out[metric] = []
        for g in groups.values():
            by_episode: dict[int, list[float]] = defaultdict(list)
            counted = metric not in COUNT_METRICS or g["explore"] not in COUNTS_NOTHING
            for run_id in g["runs"] if counted else []:
                for p in points[run_id]:
                    v = _finite(p.get(metric))
                    if v is not None and isinstance(p.get("episode"), int):
                        by_episode[p["episode"]].append(v)
            curve = {**g, "episode": [], "mean": [], "std": [], "lo": [], "hi": [], "n": []}
            for ep in sorted(by_episode):
                vs = by_episode[ep]
                mean = sum(vs) / len(vs)
                std = math.sqrt(sum((v - mean) ** 2 for v in vs) / len(vs))
                curve["episode"].append(ep)
                curve["mean"].append(mean)
                curve["std"].append(std)
                curve["lo"].append(mean - std)
                curve["hi"].append(mean + std)
                curve["n"].append(len(vs))
            out[metric].append(curve)
    return {
        "experiment": exp_id,
        "name": name,
        "band": "mean ± one standard deviation over seeds",
        "metrics": out,
    }
