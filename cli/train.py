"""`macb train`: one experiment in this process, without the bus or any service."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from cli.config_flags import (
    HelpFormatter,
    add_config_flags,
    given_config_flags,
    resolve_config,
)
from shared.config import ConfigError, load_config, make_config

if TYPE_CHECKING:  # (imported when a writer opens: tensorboard is slow to import)
    from cli.tensorboard import TensorBoardRun


def add_train_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train",
        help="run one experiment in this process",
        description="Run one experiment in one process and write DIR/metrics.csv, "
        "DIR/metrics.jsonl, DIR/config.json, DIR/provenance.json (what it ran on: code, "
        "machine, libraries, the precision the learner ran in) and DIR/checkpoint.pt (and "
        "TensorBoard events with --tensorboard). Keys come from --config "
        "(YAML or JSON) and are overridden by flags.",
        formatter_class=HelpFormatter,
    )
    p.add_argument("--config", metavar="FILE", help="YAML/JSON config file")
    p.add_argument(
        "--out",
        metavar="DIR",
        default="runs/train",
        help="output directory. One that holds this config's run goes on from its cuts "
        "(or, complete, runs nothing); one that holds another config's run is refused",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--resume",
        metavar="DIR",
        help="continue the run in DIR (its config.json is the config; no other config "
        "flags) from its newest usable cut: the same rows as if it had not stopped",
    )
    p.add_argument(
        "--cut-every",
        metavar="SECONDS",
        type=float,
        default=60.0,
        help="write a cut (everything needed to resume) at the first evaluation point "
        "after this many seconds since the last one (and 50 times the last cut's own "
        "length), and at the end",
    )
    p.add_argument(
        "--tensorboard",
        metavar="DIR",
        help="also write every metric row as TensorBoard scalars (step = episode) to "
        "DIR/<name of the output directory>/ as it is produced (tensorboard --logdir DIR)",
    )
    p.add_argument(
        "--seeds",
        type=int,
        nargs="+",
        metavar="SEED",
        help="several runs of this config, one per seed, trained as one run group in this "
        "process (each run's rows are those it gives alone), in DIR/seed-SEED/; the same "
        "command again continues them from their cuts",
    )
    add_config_flags(p)
    p.set_defaults(func=cmd_train)


class _TensorBoardRows:
    """`train`'s on_metrics for --tensorboard: the writer opens at the first row, so a
    resumed run hides (purges) what its killed life wrote from that episode on."""

    def __init__(self, folder: Path, resume: bool) -> None:
        self.folder, self.resume = folder, resume
        self.run: TensorBoardRun | None = None

    def __call__(self, row: dict) -> None:
        if self.run is None:
            from cli.tensorboard import TensorBoardRun

            purge = row["episode"] if self.resume else None
            self.run = TensorBoardRun(self.folder, fresh=not self.resume, purge_from=purge)
        self.run.write(row)

    def close(self) -> None:
        if self.run is not None:
            self.run.close()


def cmd_train(args: argparse.Namespace) -> int:
    """A bad config is refused (exit 2) before training starts or anything is written,
    and before torch is imported: a refusal answers at once."""
    if args.cut_every < 0:
        print(f"macb train: --cut-every {args.cut_every:g}: 0 or more seconds", file=sys.stderr)
        return 2
    if args.resume:
        given = ["--config"] * bool(args.config) + ["--seeds"] * bool(args.seeds)
        given += ["--out"] * (args.out != "runs/train")  # (the run's folder is DIR)
        given += given_config_flags(args)
        if given:
            flags = ", ".join(given)
            print(
                f"macb train: --resume takes the config from {args.resume}/config.json; "
                f"drop {flags}",
                file=sys.stderr,
            )
            return 2
        try:
            cfg = load_config(Path(args.resume) / "config.json")
        except (ConfigError, OSError) as err:
            print(f"macb train: cannot resume {args.resume}: {err}", file=sys.stderr)
            return 2
        out = Path(args.resume)
    else:
        try:
            cfg = resolve_config(args)
        except (ConfigError, OSError) as err:
            print(f"macb train: invalid config: {err}", file=sys.stderr)
            return 2
        out = Path(args.out)
        if args.seeds:
            return _train_seeds(args, cfg, out)
    from cli.local import device_error
    from cli.runs_folder import unwritable

    if why := device_error([cfg]):  # (before the run's folder, its lock and cuts/)
        print(f"macb train: {why}", file=sys.stderr)
        return 2
    for flag, folder in (("--tensorboard", args.tensorboard), ("--out", out)):
        if folder and (why := unwritable(Path(folder))):
            print(f"macb train: {flag} {folder}: cannot write there ({why})", file=sys.stderr)
            return 2
    resume = bool(args.resume)
    if not resume:
        # A folder that holds a run: another config's is refused (its rows are not this
        # run's); this config's goes on from its cuts, or is complete, as a run of
        # `--seeds` or `--local` does. Nothing starts a run again over one.
        from cli.local import MetricsError, config_conflict, run_rows, run_state

        if why := config_conflict(out, cfg):
            print(
                f"macb train: --out {out}: holds a run of another config ({why}); move it "
                f"away or give another --out (`macb train --resume {out}` continues that "
                "run if it stopped short)",
                file=sys.stderr,
            )
            return 2
        try:
            state = run_state(out, cfg)
            last = run_rows(out)[-1] if state == "done" else {}
        except MetricsError as err:  # (its rows do not read: nothing to go on from)
            print(f"macb train: {err}", file=sys.stderr)
            return 2
        if state == "done":
            print(
                f"{out} holds this run, complete ({last.get('episode', 0)} episodes): "
                "nothing to run (another --out trains it again)"
                + (
                    "; no TensorBoard events written: `macb export --tensorboard` writes a "
                    "stored run's"
                    if args.tensorboard
                    else ""
                )
            )
            return 0
        if state.startswith("cut-"):
            print(f"{out} holds this run: going on from its cut at episode {state[4:]}")
            resume = True
    from cli.trainer import train
    from shared.core.learners.precision import DeviceError
    from shared.persist.cuts import CutError
    from shared.persist.runlock import RunLocked
    from shared.run.rollout import WorldError

    tb = None
    if args.tensorboard:
        tb = _TensorBoardRows(Path(args.tensorboard) / out.resolve().name, resume)
    try:
        rows = train(
            cfg,
            out,
            progress=not args.quiet,
            on_metrics=tb,
            resume=resume,
            cut_every_s=args.cut_every,
        )
    except CutError as err:
        print(f"macb train: cannot resume {out}: {err}", file=sys.stderr)
        return 2
    except (DeviceError, RunLocked) as err:
        print(f"macb train: {err}", file=sys.stderr)
        return 2
    except WorldError as err:
        print(f"macb train: {err}: the run ended there (its rows up to the last point kept)",
              file=sys.stderr)  # fmt: skip
        return 2
    finally:
        if tb is not None:
            tb.close()
    last = rows[-1] if rows else {}
    if last.get("stop_reason"):  # early_stop: completed where its rule held
        print(f"ended by its rule: {last['stop_reason']} (best point in {out}/best.pt)")
    print(
        f"done: {last.get('episode', 0)} episodes, final success "
        f"{last.get('success_rate', 0):.2f}, "
        f"{last.get('steps_per_sec', 0):.1f} env steps/s "
        f"({last.get('train_steps_per_sec', 0):.1f} without evaluation); results in {out}/"
        + (f", TensorBoard events in {tb.folder}/" if tb is not None else "")
    )
    return 0


def _train_seeds(args: argparse.Namespace, cfg, out: Path) -> int:
    """`--seeds`: one run per seed as a run group, each in out/seed-S/."""
    from cli.local import LocalRun, run_groups

    if args.tensorboard:
        print("macb train: --tensorboard takes one run; drop it or --seeds", file=sys.stderr)
        return 2
    if len(set(args.seeds)) != len(args.seeds):
        print(f"macb train: --seeds {args.seeds}: a seed is given twice", file=sys.stderr)
        return 2
    try:  # each seed's config checked (a negative seed) before any runs
        seeded = {s: make_config({**cfg.model_dump(mode="json"), "seed": s}) for s in args.seeds}
    except ConfigError as err:
        print(f"macb train: --seeds {' '.join(map(str, args.seeds))}: {err}", file=sys.stderr)
        return 2
    runs = [LocalRun(f"seed-{s}", None, s, seeded[s]) for s in args.seeds]
    code = run_groups(runs, out, quiet=args.quiet, cut_every_s=args.cut_every, jobs=1)
    for r in runs:
        rows = (out / r.name / "metrics.jsonl").read_text().splitlines()
        last = json.loads(rows[-1]) if rows else {}
        ended = (
            f" (ended by its rule at episode {last['episode']})" if last.get("stop_reason") else ""
        )
        print(
            f"seed {r.seed}: final success {last.get('success_rate', 0):.2f}{ended}; "
            f"{out / r.name}/"
        )
    return code
