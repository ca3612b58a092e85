"""The figure view: a figure or an experiment as the report draws it, as JSON for a page
(services/api/figure.html), and `macb view RUNS_DIR`, a read-only server of that page
over a runs folder that follows the folder as rows are appended.

Every number comes from the report's own functions (cli/reproduce/analysis.py: smoothing,
bands, plateau, convergence, claim verdicts; controls.py: each counting arm against its
control; status.py: progress and the projected finish): this module only puts them in
JSON, so the page, FIGURE.md and `macb.summary` cannot disagree. The page draws what it
is given and computes nothing. The API serves the same JSON for an experiment
(GET /experiments/{id}/figure): `macb serve api` hands it `experiment_view`, since
services/ must not import cli/.

A runs folder of a figure (`--figure fig8 --profile thesis`) is read as `macb reproduce
--local --report-only` reads it; any other runs folder as `macb.load_runs` reads it
(cli/runs_folder.py), each arm its runs' config, with no claims, and each counting arm's
control found among the arms as for a figure (the same config with explore: constant).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import re
import socket
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cli.config_flags import HelpFormatter
from cli.reproduce.analysis import (
    BANDS,
    SMOOTH_SHARE,
    Analysis,
    Columns,
    analyse,
    claim_verdicts,
    columns,
)
from cli.reproduce.controls import control_verdicts
from cli.reproduce.defs import ArmDef, FigureDef
from cli.reproduce.experiments import (
    arm_configs,
    control_of,
    counts,
    every_arms_runs,
    figure_body,
)
from cli.reproduce.figures import FIGURES, PROFILES
from cli.reproduce.plot import figure_colors, thesis_marks
from cli.reproduce.status import FigureProgress, from_points, read_folders
from cli.runs_folder import RunsError, arm_of, read_config, read_rows, runs_in
from shared.config import error_text

# Keys of a run's config that are the run's own, not its arm's.
RUN_KEYS = ("seed",)


# ---------------------------------------------------------------- the JSON
def figure_data(a: Analysis, progress: FigureProgress, now: float) -> dict[str, Any]:
    """The page's data: per arm its smoothed mean, band and each seed's smoothed curve
    (the figure's metric), its control, plateau and convergence; the claims with their
    verdicts so far; each counting arm against its control; each run's progress and the
    projected finish."""
    fig = a.fig
    configs = arm_configs(fig)
    colors = figure_colors(a)  # the PNG's
    arms = []
    for arm_def in fig.arms:
        arm = a.arm(arm_def.name)
        low, high = arm.band() if len(arm.episodes) else (np.zeros(0), np.zeros(0))
        stack = arm.smoothed.get(fig.metric)
        seeds = [
            {"seed": s, "run": r, "values": _floats(stack[i])}
            for i, (s, r) in enumerate(zip(arm.seeds, arm.runs, strict=True))
            if stack is not None
        ]
        has = len(arm.episodes) > 0
        arms.append(
            {
                "name": arm_def.name,
                "color": colors.get(arm_def.name),
                "counts": counts(configs[arm_def.name]),
                "control": control_of(fig, arm_def.name) if counts(configs[arm_def.name]) else None,
                "is_control": configs[arm_def.name].get("explore") == "constant",
                "runs": arm.runs,
                "seeds": arm.seeds,
                "episode": [int(e) for e in arm.episodes],
                "mean": _floats(arm.curve()),
                "low": _floats(low),
                "high": _floats(high),
                "per_seed": seeds,
                "window": arm.window,
                "length": arm.length,
                "plateau": _float(arm.plateau),
                "converged": arm.converged if has else None,
                "final": _float(arm.final) if has else None,
                "describe": arm.describe(),
            }
        )
    return {
        "figure": fig.name,
        "title": fig.title,
        "metric": fig.metric,
        "episodes": fig.episodes,
        "band": fig.band,
        "band_text": BANDS[fig.band],
        "smoothing": f"a centred moving average over {SMOOTH_SHARE:.0%} of each seed's "
        "points (the window below, in points), then the mean over seeds",
        "arms": arms,
        "claims": [
            {"claim": c.text, "where": c.where, "thesis": c.thesis, "measured": m, "verdict": v}
            for c, m, v in claim_verdicts(a)
        ],
        # What the report's plot marks: each value a claim states at an episode the
        # runs were started to reach (numbered as the claims are).
        "marks": [
            {
                "claim": n,
                "arm": c.arm,
                "episode": c.episode,
                "lo": c.lo,
                "hi": c.hi,
                "thesis": claim.thesis,
            }  # fmt: skip
            for n, claim, c in thesis_marks(a)
        ],
        "controls": [
            {
                "arm": arm,
                "control": control,
                "arm_measured": mine,
                "control_measured": theirs,
                "verdict": verdict,
            }
            for arm, control, mine, theirs, verdict in control_verdicts(a)
        ],
        "progress": {
            "runs": [
                {
                    "run": r.run,
                    "arm": r.arm,
                    "seed": r.seed,
                    "episode": r.episode,
                    "target": r.target,
                    "speed": _float(r.speed),
                    "hours_left": _float(r.hours_left),
                    "note": r.note,
                }
                for r in progress.runs
            ],
            "reached": progress.reached(),
            "speeds": progress.speeds(),
            "finish": progress.finish(now),
            "done": progress.done,
        },
    }


def _float(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def _floats(values: np.ndarray) -> list[float | None]:
    return [_float(float(v)) for v in np.asarray(values, dtype=float)]


# ---------------------------------------------------------------- a figure from its runs
def runs_figure(name: str, runs: list[dict[str, Any]]) -> FigureDef:
    """A figure of whatever arms the runs have (each run: its arm and config), in the
    order first seen: each arm's config its first run's but for the run's own keys;
    no claims; the length the longest run's."""
    configs: dict[str, dict[str, Any]] = {}
    for r in runs:
        config = {k: v for k, v in (r.get("config") or {}).items() if k not in RUN_KEYS}
        configs.setdefault(r["arm"], config)
    episodes = max((int(c.get("episodes") or 0) for c in configs.values()), default=0)
    return FigureDef(
        name=name,
        title=name,
        section="",
        metric="success_rate",
        episodes=episodes,
        arms=tuple(ArmDef(n, file="", config=c) for n, c in configs.items()),
        claims=(),
    )


REPRODUCE_NAME = re.compile(r"reproduce (\S+) profile=")


def experiment_figure(exp: dict[str, Any]) -> FigureDef:
    """An API experiment's figure: a `macb reproduce FIGURE` experiment (named by
    experiment_name) is that figure, with its claims; any other, its runs' arms."""
    m = REPRODUCE_NAME.match(exp.get("name") or "")
    if m and m.group(1) in FIGURES:
        return FIGURES[m.group(1)]
    return runs_figure(exp.get("name") or exp["id"], exp["runs"])


def experiment_view(exp: dict[str, Any], points: dict[str, list[dict[str, Any]]]) -> dict:
    """The page's data for an API experiment (GET /experiments/{id}) and its runs'
    points: what GET /experiments/{id}/figure serves."""
    fig = experiment_figure(exp)
    cols = {run: columns(p) for run, p in points.items()}
    a = analyse(fig, exp, cols)
    progress = from_points(exp, cols, fig.episodes)
    return {"experiment": exp["id"], **figure_data(a, progress, time.time())}


def learned(exp: dict[str, Any], points: dict[str, list[dict[str, Any]]]) -> list[str]:
    """A line per arm saying what its runs learned, in the report's words: its success
    at the first and the last evaluation point (the mean over seeds), then its plateau
    and the episode it converged at (cli/reproduce/analysis.py's definitions)."""
    fig = runs_figure(exp.get("name") or exp["id"], exp["runs"])
    a = analyse(fig, exp, {run: columns(p) for run, p in points.items()})
    lines = []
    for name, arm in a.arms.items():
        evals = (fig.arm(name).config or {}).get("eval_episodes", "the")
        raw = arm.raw.get("success_rate")
        if raw is None or not len(raw):
            lines.append(f"what was learned ({name}): nothing yet, no evaluation point")
            continue
        first, last = int(arm.episodes[0]), int(arm.episodes[-1])
        lines.append(
            f"what was learned ({name}): success {raw[0]:.0%} at episode {first:,} -> "
            f"{raw[-1]:.0%} at episode {last:,} (of {evals} noise-free evaluation episodes"
            f"{', mean over seeds' if len(arm.seeds) > 1 else ''}); {arm.describe()}"
        )
    return lines


# ---------------------------------------------------------------- a runs folder
@dataclass
class _Run:
    id: str
    arm: str
    seed: int
    folder: Path
    config: dict[str, Any]


class FolderView:
    """A runs folder's figure view, read again when a run's metrics file changes (its
    size and modification time: rows are only appended), each run's rows read again
    only when its own file changed."""

    def __init__(self, root: Path, figure: FigureDef | None = None, body: dict | None = None):
        self.root = root
        self.fig = figure
        self.body = body
        self.runs_dir = root / "runs" if (root / "runs").is_dir() else root
        self._rows: dict[str, tuple[tuple[int, int], Columns]] = {}
        self._data: tuple[str, dict[str, Any]] | None = None
        self._lock = threading.Lock()
        if figure is None:
            runs_in(root)  # RunsError now, not at the first request

    def _runs(self) -> tuple[str, list[int], list[_Run], list[Any]]:
        if self.fig is not None and self.body is not None:
            from cli.local import expand_body

            name, seeds, local = expand_body(self.body)
            runs = [
                _Run(
                    r.name,
                    r.arm or r.name,
                    r.seed,
                    self.runs_dir / r.name,
                    r.config.model_dump(mode="json"),
                )  # fmt: skip
                for r in local
            ]
            return name, seeds, runs, local
        folders, recorded = runs_in(self.root)
        runs = []
        for f in folders:
            config = read_config(f)
            seed = int(config.get("seed") or 0)
            runs.append(_Run(f.name, recorded.get(f.name) or arm_of(f, seed), seed, f, config))
        return self.root.resolve().name, sorted({r.seed for r in runs}), runs, []

    @staticmethod
    def _stamp(folder: Path) -> tuple[int, int]:
        for name in ("metrics.jsonl", "metrics.csv"):
            path = folder / name
            if path.is_file():
                st = path.stat()
                return st.st_size, st.st_mtime_ns
        return 0, 0

    def _columns(self, run: _Run) -> Columns:
        stamp = self._stamp(run.folder)
        kept = self._rows.get(run.id)
        if kept is None or kept[0] != stamp:
            rows = read_rows(run.folder) if stamp != (0, 0) else []
            kept = (stamp, columns(rows))
            self._rows[run.id] = kept
        return kept[1]

    def data(self) -> tuple[str, dict[str, Any]]:
        """(version, the page's data), computed again only when the version changed."""
        with self._lock:
            name, seeds, runs, local = self._runs()
            # each run's arm and config too: a reproduce's FIGURE-runs.json written (or a
            # config.json rewritten) since the last request renames an arm or changes a run
            stamps = ";".join(
                f"{r.id}:{r.arm}:{json.dumps(r.config, sort_keys=True)}:{self._stamp(r.folder)}"
                for r in runs
            )
            version = hashlib.sha256(stamps.encode()).hexdigest()[:16]
            if self._data is not None and self._data[0] == version:
                return self._data
            described: list[dict[str, Any]] = [
                {"id": r.id, "arm": r.arm, "seed": r.seed, "config": r.config} for r in runs
            ]
            exp = {"id": f"folder:{self.root}", "name": name, "seeds": seeds, "runs": described}
            fig = self.fig or runs_figure(name, described)
            points = {r.id: self._columns(r) for r in runs}
            a = analyse(fig, exp, points)
            if local:
                progress = read_folders(local, self.runs_dir, fig.episodes)
            else:
                progress = from_points(exp, points, fig.episodes)
            data = {"folder": str(self.root), **figure_data(a, progress, time.time())}
            self._data = (version, data)
            return self._data


# ---------------------------------------------------------------- the command
def add_view_parser(sub: argparse._SubParsersAction) -> None:
    vp = sub.add_parser(
        "view",
        help="serve a runs folder's figure as the report draws it, following new rows",
        description="A read-only page of RUNS_DIR's runs as the report draws them: each "
        "arm's smoothed mean and band, each counting arm beside its constant control, each "
        "seed's curve on demand, the claims' verdicts so far (with --figure), each run's "
        "progress and the projected finish. It reads the folder again as rows are "
        "appended (a `macb train`, `--local` or Slurm campaign running into it).",
        formatter_class=HelpFormatter,
    )
    vp.add_argument("runs_dir", metavar="RUNS_DIR", help="a runs folder or a reproduce's OUT")
    vp.add_argument("--figure", choices=list(FIGURES), help="the figure these runs are of")
    vp.add_argument("--profile", choices=PROFILES, default="mpe2", help="with --figure")
    vp.add_argument("--arms", nargs="+", metavar="PATTERN", help="with --figure: as reproduce's")
    vp.add_argument("--seeds", type=int, nargs="+", metavar="SEED", help="with --figure")
    vp.add_argument("--episodes", type=int, metavar="N", help="with --figure: the runs' length")
    vp.add_argument("--precision", choices=("fp32", "bf16"), help="with --figure")
    vp.add_argument("--threads", type=int, metavar="N", help="with --figure: as reproduce's")
    vp.add_argument("--device", metavar="DEVICE", help="with --figure: as reproduce's")
    vp.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on; there is no token: whoever reaches it reads the runs "
        "(from elsewhere, prefer an SSH tunnel to loopback)",
    )
    vp.add_argument("--port", type=int, default=8100, help="port (0: any free one)")
    vp.set_defaults(func=cmd_view)


def folder_view(args: argparse.Namespace) -> FolderView:
    """The view of args.runs_dir: RunsError / ValueError when it cannot be one."""
    root = Path(args.runs_dir)
    if args.figure is None:
        figure_only = ("arms", "seeds", "episodes", "precision", "threads", "device")
        if extra := [f"--{k}" for k in figure_only if getattr(args, k, None) is not None]:
            raise ValueError(f"{', '.join(extra)}: only with --figure (they say its runs)")
        return FolderView(root)
    fig = FIGURES[args.figure]
    given = {"threads": None, "device": None, **vars(args)}  # a caller's may lack those two
    flags = argparse.Namespace(**{**given, "local": True, "report_only": False, "status": False})
    if not root.is_dir():
        raise RunsError(f"{root}: {'a file, not a folder' if root.exists() else 'no such folder'}")
    view = FolderView(root, fig, figure_body(fig, flags))
    from cli.local import TRAINED_WITH, config_conflicts, expand_body, foreign_runs

    runs = expand_body(view.body or {})[2]
    if why := foreign_runs(runs, view.runs_dir, every_arms_runs(fig, flags)):
        raise RunsError(why)
    if conflicts := config_conflicts(runs, view.runs_dir):
        raise RunsError("; ".join(conflicts) + f": {TRAINED_WITH} or another folder")
    return view


def cmd_view(args: argparse.Namespace) -> int:
    import uvicorn

    from cli.view_app import page_app

    try:
        view = folder_view(args)
        view.data()
    except (RunsError, ValueError, OSError) as err:
        print(f"macb view: {error_text(err)}", file=sys.stderr)
        return 2
    if not 0 <= args.port <= 65535:
        print(f"macb view: --port {args.port}: a port is from 0 to 65535", file=sys.stderr)
        return 2
    # Bound here, so that a port in use or a host not of this machine is refused (exit
    # 2) before the server starts, and the server takes this very socket.
    sock = socket.socket(socket.AF_INET6 if ":" in args.host else socket.AF_INET)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((args.host, args.port))
    except (OSError, OverflowError) as err:
        sock.close()
        why = getattr(err, "strerror", None) or err
        print(f"macb view: cannot listen on {args.host}:{args.port} ({why})", file=sys.stderr)
        return 2
    config = uvicorn.Config(
        page_app(view), host=args.host, port=args.port, log_level="warning", access_log=False
    )
    server = uvicorn.Server(config)

    def announce() -> None:
        while not server.started:
            time.sleep(0.05)
        port = server.servers[0].sockets[0].getsockname()[1]
        print(f"macb view: http://{args.host}:{port}/ (Ctrl-C stops it)", flush=True)

    threading.Thread(target=announce, daemon=True).start()
    server.run(sockets=[sock])
    return 0
