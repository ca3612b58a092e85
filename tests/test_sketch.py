"""`count_sketch`: a run's counts in a count-min sketch of fixed memory.

The sketch never counts below the truth and, on a real speaker-listener stream hashed
by the run's own SimHash, stays within count-min's bound; conservative update never
counts above the plain sketch; how rows are batched and which process hashes them
change nothing; cuts, the counter's snapshot and log, and `macb train --resume` give it
back bit for bit; invalid sizes are refused naming the field. (A group's runs and the
lockstep cluster: tests/test_group_trainer.py, tests/test_lockstep.py.)
"""

from __future__ import annotations

import json
import logging
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from cli.trainer import load_checkpoint, train
from services.counter import snapshot
from services.counter.state import RunState
from shared.config import ConfigError, make_config
from shared.core.counting import CountSketch, CountTable, sketch_bound, sketch_shape
from shared.envs.tasks import make_task_for, task_spec_for
from shared.persist.checkpoint import CutError, load_tables, tables_state
from shared.persist.wal import WriteAheadLog
from shared.run.factories import build_exploration
from shared.run.rollout import make_collector

ROOT = Path(__file__).resolve().parent.parent


def stream(n: int, distinct: int, key_bytes: int = 8, seed: int = 0) -> np.ndarray:
    """n keys drawn from `distinct` ones, Zipf-like: a few common, many rare."""
    rng = np.random.default_rng(seed)
    pool = rng.integers(0, 256, size=(distinct, key_bytes), dtype=np.uint8)
    return pool[np.minimum(rng.zipf(1.3, size=n) - 1, distinct - 1)]


def test_a_sketch_never_counts_below_the_truth_and_conservative_never_above_plain():
    keys = stream(6000, 3000)
    exact, cu, plain = CountTable(8), CountSketch(8, 97, 3, seed=1), CountSketch(8, 97, 3, 1, False)
    for table in (exact, cu, plain):
        table.increment(keys)
    true, est_cu, est_plain = exact.counts(keys), cu.counts(keys), plain.counts(keys)
    assert (est_cu >= true).all() and (est_plain >= est_cu).all()
    assert (plain.cells >= cu.cells).all() and (est_plain > est_cu).any()  # it does tighten
    assert (est_cu > true).any()  # 97 columns for ~1,500 keys: collisions happen
    assert plain.cells.sum() == 3 * len(keys) and cu.total == plain.total == len(keys)
    assert len(cu) <= len(exact) and 0 <= cu.count1 <= len(cu)
    # wide enough for no collision: the sketch is the table
    wide = CountSketch(8, 1 << 24, 4, seed=1)
    wide.increment(keys)
    assert np.array_equal(wide.counts(keys), true)
    assert (len(wide), wide.count1, wide.count1_pct) == (len(exact), exact.count1, exact.count1_pct)


@pytest.mark.parametrize("conservative", [True, False])
@pytest.mark.parametrize(("width", "distinct"), [(53, 500), (4099, 2500)])
def test_how_rows_are_batched_changes_nothing(conservative, width, distinct):
    """Bursts of any size (the counter's) give the sketch of one row at a time (macb
    train's), cells, estimated keys and count-1 keys alike: narrow (most rows share
    cells: row by row) and wide (waves of independent rows counted at once)."""
    keys = stream(3000, distinct, key_bytes=7)  # an odd key width is padded
    one = CountSketch(7, width, 4, seed=5, conservative=conservative)
    for i in range(len(keys)):
        one.increment(keys[i : i + 1])
    rng = np.random.default_rng(1)
    for parts in (40, 5):
        bursts = CountSketch(7, width, 4, seed=5, conservative=conservative)
        cuts = np.sort(rng.choice(np.arange(1, len(keys)), size=parts, replace=False))
        for part in np.split(keys, cuts):
            bursts.increment(part)
        assert np.array_equal(bursts.cells, one.cells)
        assert (len(bursts), bursts.count1, bursts.total) == (len(one), one.count1, one.total)
    whole = CountSketch(7, width, 4, seed=5, conservative=conservative)
    whole.increment(keys)
    assert np.array_equal(whole.cells, one.cells) and whole.count1 == one.count1


def test_the_hash_is_the_same_in_another_process_whatever_its_hash_seed():
    keys = stream(50, 50, key_bytes=128, seed=3)
    mine = CountSketch(128, 1 << 20, 4, seed=11).cells_of(keys).tolist()
    code = (
        "import json, sys, numpy as np\n"
        "from shared.core.counting import CountSketch\n"
        "keys = np.array(json.loads(sys.stdin.read()), dtype=np.uint8)\n"
        "print(json.dumps(CountSketch(128, 1 << 20, 4, seed=11).cells_of(keys).tolist()))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        input=json.dumps(keys.tolist()),
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={"PYTHONHASHSEED": "12345", "PATH": "/usr/bin:/bin"},
        check=True,
    )
    assert json.loads(out.stdout) == mine
    assert CountSketch(128, 1 << 20, 4, seed=12).cells_of(keys).tolist() != mine  # seeded


def speaker_listener_keys(k: int, steps: int) -> np.ndarray:
    """SimHash keys of a real speaker-listener rollout (Cen-MACB's joint s||a, the run's
    own projection), uniform random actions as in the thesis code's warm-up."""
    cfg = make_config(
        {"explore": "cen-macb", "k": k, "warmup": "random", "learning_starts": 10**9, "seed": 4}
    )
    env = make_task_for(cfg)
    collector = make_collector(cfg, env)
    rows = [collector.step(lambda obs: obs) for _ in range(steps)]
    obs = np.stack([r.obs for r in rows])
    act = np.stack([r.act for r in rows])
    explorer = build_exploration(cfg, task_spec_for(cfg))
    return explorer.keys(obs, act)[0]


@pytest.mark.parametrize(("k", "eps", "delta"), [(8, 0.05, 0.05), (512, 0.0005, 0.05)])
def test_the_error_bound_holds_on_a_real_speaker_listener_stream(k, eps, delta):
    """Every estimate >= the exact count, and above exact + eps * N for at most a share
    delta of the keys (the bound is per key, with probability 1 - delta), at width =
    ceil(e / eps), depth = ceil(ln 1 / delta). k = 8: few keys, counts in the hundreds;
    k = 512 (the thesis's): nearly every key new. Both sketches are small enough for
    collisions to change most or some estimates; conservative update changes fewer."""
    keys = speaker_listener_keys(k, 4000)
    n = len(keys)
    width, depth = sketch_shape(eps, delta)
    eps, delta = sketch_bound(width, depth)  # what this width and depth guarantee
    exact = CountTable(keys.shape[1])
    exact.increment(keys)
    if k == 8:
        assert len(exact) < n / 10  # counts well above 1: a real test of the estimate
    else:
        assert len(exact) > 0.99 * n
    _, first = np.unique(keys, axis=0, return_index=True)
    distinct = keys[np.sort(first)]
    true = exact.counts(distinct)
    errors = {}
    for conservative in (True, False):
        sketch = CountSketch(keys.shape[1], width, depth, seed=9, conservative=conservative)
        sketch.increment(keys)
        est = sketch.counts(distinct)
        assert (est >= true).all()
        assert np.mean(est > true + eps * n) <= delta, conservative
        # a row's expected overestimate is at most N / width; the min over rows is less
        assert (est - true).mean() <= n / width
        errors[conservative] = est - true
    assert (errors[True] > 0).any()  # collisions did happen
    assert (errors[True] <= errors[False]).all() and errors[True].sum() < errors[False].sum()


def test_a_sketch_survives_a_cut_and_another_shape_or_kind_is_refused(tmp_path):
    keys = stream(500, 200)
    sketch = CountSketch(8, 61, 3, seed=2)
    sketch.increment(keys)
    torch.save({"tables": tables_state([sketch])}, tmp_path / "cut.pt")
    state = torch.load(tmp_path / "cut.pt", weights_only=True)["tables"]
    again = [CountSketch(8, 61, 3, seed=2)]
    load_tables(again, state, tmp_path / "cut.pt")  # type: ignore[arg-type]
    back = again[0]
    assert isinstance(back, CountSketch) and np.array_equal(back.cells, sketch.cells)
    assert (back.total, len(back), back.count1) == (sketch.total, len(sketch), sketch.count1)
    with pytest.raises(CutError, match=r"cut.pt: table 0: width 61 in the snapshot, 62 here"):
        load_tables([CountSketch(8, 62, 3, seed=2)], state, tmp_path / "cut.pt")
    with pytest.raises(CutError, match="is a count-min sketch, the run has an exact table"):
        load_tables([CountTable(8)], state, tmp_path / "cut.pt")
    exact = CountTable(8)
    exact.increment(keys)
    with pytest.raises(CutError, match="is an exact table, the run has a count-min sketch"):
        load_tables([CountSketch(8, 61, 3, seed=2)], tables_state([exact]), tmp_path / "c.pt")


@pytest.mark.parametrize(
    ("sketch", "message"),
    [
        ({"width": 0}, "count_sketch.width: Input should be greater than or equal to 1"),
        ({"width": 2**30 + 1}, "count_sketch.width: Input should be less than or equal to"),
        ({"width": 100, "depth": 0}, "count_sketch.depth: Input should be greater than or equal"),
        ({"width": 100, "depth": 33}, "count_sketch.depth: Input should be less than or equal"),
        ({}, "count_sketch: give width or memory_mb (one of them)"),
        ({"width": 100, "memory_mb": 4}, "count_sketch: give width or memory_mb (one of them)"),
        ({"memory_mb": 0}, "count_sketch.memory_mb: Input should be greater than 0"),
        ({"memory_mb": 1e-7}, "count_sketch: memory_mb 1e-07 holds not one column"),
        ({"width": 2**30, "depth": 4}, "count_sketch: width 1073741824 x depth 4 is over"),
        ({"width": 100, "rows": 3}, "count_sketch.rows: unknown key"),
    ],
)
def test_invalid_sketch_sizes_are_refused_naming_the_field(sketch, message):
    with pytest.raises(ConfigError) as err:
        make_config({"count_sketch": sketch})
    assert message in str(err.value)


def test_the_exact_table_is_the_default_and_memory_mb_sets_the_width():
    cfg = make_config({})
    assert cfg.count_sketch is None
    explorer = build_exploration(cfg, task_spec_for(cfg))
    assert all(isinstance(t, CountTable) for t in explorer.tables)
    cfg = make_config({"explore": "dis-macb", "count_sketch": {"memory_mb": 16}})
    assert cfg.count_sketch is not None and cfg.count_sketch.columns == 2**20
    explorer = build_exploration(cfg, task_spec_for(cfg))
    assert len(explorer.tables) == 2 and all(isinstance(t, CountSketch) for t in explorer.tables)
    assert [t.memory_bytes() // 2**20 for t in explorer.tables] == [16, 16]
    a, b = explorer.tables
    assert isinstance(a, CountSketch) and isinstance(b, CountSketch)
    assert not np.array_equal(a._a, b._a)  # each table hashes with a seed of its own


def counter_run(path: Path, cfg) -> RunState:
    spec = task_spec_for(cfg)
    path.mkdir(parents=True, exist_ok=True)
    wal, _ = WriteAheadLog.open(path / "log.wal")
    explorer = build_exploration(cfg, spec)
    return RunState(cfg, explorer, spec.joint_obs_dim, spec.joint_act_dim, path, wal)


def test_the_counters_snapshot_and_log_give_the_sketch_back_bit_for_bit(tmp_path):
    """The counter's exactly-once path with a sketch: a snapshot, the log beyond it
    replayed (a duplicate record dropped by its sequence number), equal to counting
    the rows straight."""
    cfg = make_config({"explore": "cen-macb", "k": 8, "count_sketch": {"width": 31}})
    st = counter_run(tmp_path / "r", cfg)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(60, st.obs_dim)).astype(np.float32).round(1)
    act = rng.uniform(size=(60, st.act_dim)).astype(np.float32).round(1)

    def count(st: RunState, seq: int, n: int) -> None:
        keys = st.explorer.keys(obs[seq : seq + n], act[seq : seq + n])
        st.wal.append_many([("a0", seq, n, keys)])
        for table, k in zip(st.explorer.tables, keys):
            table.increment(k)
        st.cursor.take("a0", seq, n)
        st.counted += n

    count(st, 0, 25)
    snapshot.write("r", st)
    count(st, 25, 20)
    count(st, 45, 15)
    st.wal.close()
    again = counter_run(tmp_path / "r", cfg)
    _, records = WriteAheadLog.open(tmp_path / "r" / "log.wal")
    snapshot.load(again)
    assert snapshot.replay("r", again, records + records, logging.getLogger("t")) == 2
    straight = build_exploration(cfg, task_spec_for(cfg))
    straight.observe(obs, act)
    for got, want in zip(again.explorer.tables, straight.tables):
        assert isinstance(got, CountSketch) and isinstance(want, CountSketch)
        assert np.array_equal(got.cells, want.cells) and got.count1 == want.count1
    assert again.counted == 60 and again.explorer.stats() == straight.stats()
    assert snapshot.size(again) == 31 * 4 * 4  # the cells, however many keys


BASE = {
    "task": "speaker_listener",
    "episodes": 8,
    "eval_every": 2,
    "hidden": [32, 32],
    "batch_size": 16,
    "eval_episodes": 3,
    "k": 16,
    "learner_lanes": 1,
    "count_sketch": {"width": 64, "depth": 3},  # 160 transitions: collisions change counts
}
TIMING = ("steps_per_sec", "train_steps_per_sec", "wall_s")


def strip(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMING} for r in rows]


def test_macb_train_with_a_sketch_resumes_to_the_rows_of_not_stopping(tmp_path):
    cfg = make_config(BASE)
    rows = train(cfg, tmp_path / "straight", progress=False, cut_every_s=0)
    exact = train(make_config({**BASE, "count_sketch": None}), tmp_path / "exact", progress=False)
    assert strip(rows) != strip(exact)  # the sketch is in use, and its collisions show
    assert [r["counted_transitions"] for r in rows] == [r["counted_transitions"] for r in exact]
    out = tmp_path / "stopped"
    train(cfg, out, progress=False, cut_every_s=0, stop_when=lambda r: r["episode"] == 4)
    resumed = train(cfg, out, progress=False, cut_every_s=0, resume=True)
    assert strip(resumed) == strip(rows)
    got, want = (load_checkpoint(p / "checkpoint.pt") for p in (out, tmp_path / "straight"))
    cells = [c["tables"]["table0"]["sketch"]["cells"] for c in (got, want)]
    assert cells[0].shape == (3, 64) and torch.equal(cells[0], cells[1])
    other = make_config({**BASE, "count_sketch": {"width": 65, "depth": 3}})
    with pytest.raises(CutError, match="count_sketch"):
        train(other, out, progress=False, resume=True)


def test_the_bound_helpers_invert_each_other():
    for eps, delta in ((0.01, 0.05), (1e-6, 1e-3)):
        width, depth = sketch_shape(eps, delta)
        e2, d2 = sketch_bound(width, depth)
        assert e2 <= eps and d2 <= delta
        assert width == math.ceil(math.e / eps) and depth == math.ceil(math.log(1 / delta))
