"""`macb train --resume`: a one-process run continued from its cut gives the rows that not
stopping gives, bit for bit (timing columns aside), and bad cuts are refused by name."""

from __future__ import annotations

import json
import os
import signal
import time
from pathlib import Path

import pytest
import torch

from cli.main import main
from cli.trainer import load_checkpoint, train
from shared.config import make_config
from shared.persist.checkpoint import CutError
from shared.persist.cuts import CUT_FORMAT, cut_files
from tests.harness import spawn

TIMING = ("steps_per_sec", "train_steps_per_sec", "wall_s")
BASE = {
    "task": "speaker_listener",
    "episodes": 12,
    "eval_every": 2,
    "hidden": [32, 32],
    "batch_size": 16,
    "eval_episodes": 3,
    "k": 32,
    "learner_lanes": 1,  # a fixed lane count: bit-identical reruns
}


def strip(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMING} for r in rows]


def jsonl(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def straight(tmp_path_factory):
    """The uninterrupted runs each resumed run must match, by config."""
    cache: dict[str, tuple[list[dict], dict]] = {}

    def get(**extra) -> tuple[list[dict], dict]:
        key = json.dumps(extra, sort_keys=True)
        if key not in cache:
            out = tmp_path_factory.mktemp("straight")
            rows = train(make_config({**BASE, **extra}), out, progress=False, cut_every_s=0)
            cache[key] = (rows, load_checkpoint(out / "checkpoint.pt"))
        return cache[key]

    return get


@pytest.mark.parametrize(
    "extra",
    [
        {},
        {"profile": "thesis"},  # success resets, random warm-up, per-agent minibatches
        {"task": "spread", "algo": "dis-maddpg", "explore": "dis-macb"},
        {"task": "simple", "algo": "ddpg", "explore": "constant"},
    ],
    ids=["speaker_listener", "thesis-profile", "spread-dis", "simple-constant"],
)
def test_resuming_at_a_cut_gives_the_rows_of_not_stopping_bit_for_bit(tmp_path, straight, extra):
    rows, final = straight(**extra)
    cfg = make_config({**BASE, **extra})
    stopped = train(
        cfg, tmp_path, progress=False, cut_every_s=0, stop_when=lambda r: r["episode"] == 6
    )
    assert [r["episode"] for r in stopped] == [2, 4, 6]
    resumed = train(cfg, tmp_path, progress=False, cut_every_s=0, resume=True)
    assert strip(resumed) == strip(rows)
    assert strip(jsonl(tmp_path)) == strip(rows)  # every point once, in order
    got = load_checkpoint(tmp_path / "checkpoint.pt")
    assert got["counters"] == final["counters"]
    for key in ("actors", "critics", "critic_targets"):
        for a, b in zip(got["learner"][key], final["learner"][key], strict=True):
            assert all(torch.equal(a[n], b[n]) for n in a), key
    assert [int(t["counts"].sum()) for t in got["tables"].values()] == [
        int(t["counts"].sum()) for t in final["tables"].values()
    ]


def test_a_killed_macb_train_resumes_to_the_same_rows(tmp_path, straight):
    """SIGKILL of a real `macb train` process after a few cuts, then `--resume DIR`."""
    cfg = {**BASE, "episodes": 40}
    rows, _ = straight(episodes=40)
    out = tmp_path / "run"
    proc = spawn("train", "--out", str(out), "--quiet", "--cut-every", "0", *_argv(cfg))
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            cuts = cut_files(out / "cuts") if (out / "cuts").exists() else []
            if cuts and int(cuts[0].stem.split("-")[1]) >= 10:
                break
            assert proc.poll() is None, "the run ended before it could be killed"
            time.sleep(0.02)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    killed_at = len(jsonl(out))
    assert killed_at < len(rows), "killed too late to test anything"
    assert main(["train", "--resume", str(out), "--quiet", "--cut-every", "0"]) == 0
    assert strip(jsonl(out)) == strip(rows)


def _argv(cfg: dict) -> list[str]:
    """`macb train`'s flags for the keys of `cfg`."""
    argv: list[str] = []
    for k, v in cfg.items():
        argv += [
            f"--{k.replace('_', '-')}",
            ",".join(map(str, v)) if isinstance(v, list) else str(v),
        ]
    return argv


def test_train_into_a_folder_holding_a_run_goes_on_with_this_config_and_refuses_another(
    tmp_path, straight, capsys
):
    """`macb train --out DIR` over a run: this config's goes on from its cut to the rows of
    not stopping, and once complete runs nothing; another config's is refused naming the
    key, with nothing written, rather than trained over from episode 0."""
    rows, _ = straight()
    out = tmp_path / "run"
    train(make_config(BASE), out, progress=False, cut_every_s=0,
          stop_when=lambda r: r["episode"] == 6)  # fmt: skip
    argv = ["train", "--out", str(out), "--quiet", "--cut-every", "0", *_argv(BASE)]
    assert main(argv) == 0
    assert "going on from its cut at episode 6" in capsys.readouterr().out
    assert strip(jsonl(out)) == strip(rows)
    before = {f.name: f.read_bytes() for f in out.iterdir() if f.is_file()}
    assert main(argv) == 0
    assert "complete (12 episodes): nothing to run" in capsys.readouterr().out
    assert main([*argv, "--k", "64"]) == 2
    err = capsys.readouterr().err
    assert f"--out {out}: holds a run of another config (k: 32 in the folder, 64" in err
    assert {f.name: f.read_bytes() for f in out.iterdir() if f.is_file()} == before
    lines = (out / "metrics.jsonl").read_text().splitlines()  # two writers' garbage
    (out / "metrics.jsonl").write_text("\n".join([lines[0], "not json", *lines[1:]]) + "\n")
    assert main(argv) == 2
    assert "metrics.jsonl, line 2" in capsys.readouterr().err


def test_a_corrupt_newest_cut_is_refused_by_name_and_the_one_before_is_used(
    tmp_path, straight, caplog
):
    rows, _ = straight()
    cfg = make_config(BASE)
    train(cfg, tmp_path, progress=False, cut_every_s=0, stop_when=lambda r: r["episode"] == 6)
    newest, older = cut_files(tmp_path / "cuts")
    newest.write_bytes(newest.read_bytes()[:100])  # truncated mid-write (say)
    with caplog.at_level("WARNING", logger="macb.cuts"):
        resumed = train(cfg, tmp_path, progress=False, cut_every_s=0, resume=True)
    assert newest.name in caplog.text and "unreadable" in caplog.text
    assert strip(resumed) == strip(rows)  # from episode 4's cut, the same rows again
    assert newest.with_name(newest.name + ".refused").exists()


def test_a_cut_from_another_config_or_format_is_refused_naming_it_and_nothing_changes(
    tmp_path, capsys
):
    cfg = make_config(BASE)
    train(cfg, tmp_path, progress=False, cut_every_s=0, stop_when=lambda r: r["episode"] == 4)
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    edited = {**json.loads((tmp_path / "config.json").read_text()), "k": 64}
    (tmp_path / "config.json").write_text(json.dumps(edited))
    assert main(["train", "--resume", str(tmp_path), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "k: 32 in the cut, 64 in the run" in err
    (tmp_path / "config.json").write_bytes(before[tmp_path / "config.json"])
    for path in cut_files(tmp_path / "cuts"):
        state = torch.load(path, weights_only=True)
        torch.save({**state, "format": CUT_FORMAT + 1}, path)
    assert main(["train", "--resume", str(tmp_path), "--quiet"]) == 2
    assert f"cut format {CUT_FORMAT + 1}" in capsys.readouterr().err
    after = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    changed = {p for p in after if before.get(p) != after[p]} - set(cut_files(tmp_path / "cuts"))
    assert changed == set() and set(after) == set(before)  # no file written or renamed


def test_resume_refuses_config_flags(tmp_path, capsys):
    assert main(["train", "--resume", str(tmp_path), "--k", "64", "--quiet"]) == 2
    assert "drop --k" in capsys.readouterr().err


def test_a_run_stopped_after_its_first_point_resumes(tmp_path):
    """The first evaluation point is cut, whatever --cut-every says: a run killed in its
    first minute can be continued."""
    cfg = make_config({"task": "simple", "algo": "ddpg", "episodes": 3, "hidden": [16, 16],
                       "learner_lanes": 1, "learning_starts": 10})  # fmt: skip
    out = tmp_path / "run"

    class Stop(Exception):
        pass

    def stop(row):
        if row["episode"] == 2:
            raise Stop

    with pytest.raises(Stop):
        train(cfg, out, progress=False, on_metrics=stop, cut_every_s=1e9)
    assert [p.name for p in (out / "cuts").glob("cut-*.pt")] == ["cut-000000001.pt"]
    resumed = train(cfg, out, progress=False, resume=True)
    straight = train(cfg, tmp_path / "straight", progress=False)
    drop = ("steps_per_sec", "train_steps_per_sec", "wall_s")
    assert [{k: v for k, v in r.items() if k not in drop} for r in resumed] == [
        {k: v for k, v in r.items() if k not in drop} for r in straight
    ]


def test_a_cut_written_before_a_config_key_existed_still_resumes(tmp_path):
    """A key the saved config lacks counts as its default: a run from before the key
    (here `device` and `bonus_at`) resumes; one that differs from the default is still
    refused, naming it."""
    from shared.persist.checkpoint import config_difference

    cfg = make_config({"task": "simple", "algo": "ddpg"}).model_dump(mode="json")
    old = {k: v for k, v in cfg.items() if k not in ("device", "bonus_at")}
    assert config_difference(old, cfg) is None
    assert "device" in config_difference(old, {**cfg, "device": "cuda"})
    assert "beta" in config_difference({**old, "beta": 0.1}, cfg)


def test_a_run_folder_of_another_config_or_an_unreadable_one_is_refused_naming_it(tmp_path, capsys):
    """One rule for a run folder (`folder_config_difference`: the local runner, the
    trainer's resume and the counter ask it): no config.json yet or the same config goes
    on; another config names its field; a config.json that does not read, or holds no
    map, is named, never taken for an empty folder. The resume refuses before it
    writes anything."""
    from shared.persist.checkpoint import folder_config_difference

    cfg = make_config(BASE).model_dump(mode="json")
    assert folder_config_difference(tmp_path, cfg) is None  # (nothing there yet)
    (tmp_path / "config.json").write_text(json.dumps(cfg))
    assert folder_config_difference(tmp_path, cfg) is None
    why = folder_config_difference(tmp_path, {**cfg, "seed": 9})
    assert why == f"seed: {cfg['seed']!r} in the folder, 9 in the run"
    (tmp_path / "config.json").write_text('{"task": "simple", ')
    assert "config.json does not read" in folder_config_difference(tmp_path, cfg)
    (tmp_path / "config.json").write_text("[1, 2]")
    assert "config.json holds no config" in folder_config_difference(tmp_path, cfg)

    run = tmp_path / "run"
    train(
        make_config(BASE), run, progress=False, cut_every_s=0, stop_when=lambda r: r["episode"] == 3
    )
    (run / "config.json").write_text("{not json")
    before = {p: p.read_bytes() for p in run.rglob("*") if p.is_file()}
    with pytest.raises(CutError, match="holds a run of another config .*config.json does not"):
        train(make_config(BASE), run, progress=False, resume=True)
    assert main(["train", "--resume", str(run), "--quiet"]) == 2  # (reads it for the config)
    assert f"{run / 'config.json'}: not valid" in capsys.readouterr().err
    assert {p: p.read_bytes() for p in run.rglob("*") if p.is_file()} == before


def test_a_run_with_columnar_replay_files_resumes_and_keeps_one_replay_log(tmp_path, straight):
    """A run written before the record log kept its replay rows as one float32 file per
    field: it resumes to the same rows, its rows rewritten once as cuts/replay.log."""
    import numpy as np

    from shared.envs.tasks import make_task_for
    from shared.persist.cuts import ReplayLog

    rows, _ = straight()
    cfg = make_config(BASE)
    train(cfg, tmp_path, progress=False, cut_every_s=0, stop_when=lambda r: r["episode"] == 6)
    cuts = tmp_path / "cuts"
    cut = torch.load(cut_files(cuts)[0], weights_only=True)
    n = int(cut["replay_rows"])
    spec = make_task_for(cfg).spec
    obs, act = spec.joint_obs_dim, spec.joint_act_dim
    width = {"obs": obs, "act": act, "rew": 1, "next_obs": obs, "done": 1}
    data = ReplayLog(cuts).read(n, width, cuts)
    for name, values in data.items():  # as the columnar format held them
        np.ascontiguousarray(values, np.float32).tofile(cuts / f"replay.{name}.f32")
    (cuts / "replay.log").unlink()
    resumed = train(cfg, tmp_path, progress=False, cut_every_s=0, resume=True)
    assert strip(resumed) == strip(rows)
    assert sorted(p.name for p in cuts.glob("replay.*")) == ["replay.log"]
