"""The learner service's pure parts in process, no bus: exactly-once intake (held until
counted, replay once, duplicates and gaps not taken), episode boundaries, and a
checkpoint plus the log giving back the same state after a restart."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from services.learner import checkpoint as ckpt
from services.learner import intake
from services.learner.evaluations import EvaluationsInFlight
from services.learner.state import LearnerRun
from services.learner.state import new_run as new_learner_run
from shared.config import make_config
from shared.envs.tasks import task_spec_for
from shared.net.messages import Transitions
from shared.net.wire import WireError
from shared.run.factories import build_learner

LEN = 5
ACTORS = ["a0", "a1"]


def new_run(tmp_path, explore: str = "cen-macb") -> LearnerRun:
    cfg = make_config({"task": "speaker_listener", "explore": explore, "episodes": 8,
                       "episode_len": LEN, "hidden": [16, 16], "learning_starts": 3,
                       "learner_lanes": 1})  # fmt: skip
    spec = task_spec_for(cfg)
    folder = tmp_path / "learner" / "r"
    folder.mkdir(parents=True, exist_ok=True)
    return new_learner_run(
        "r", cfg, spec, ACTORS, learner=build_learner(cfg, spec), bonus=None,  # type: ignore[arg-type]
        evaluations=EvaluationsInFlight(), pubs=dict.fromkeys(("weights", "eval", "ack"), print),
        counter="c", folder=folder,
    )  # fmt: skip


def batch(st: LearnerRun, actor: str, seq: int, n: int = LEN, obs_dim: int | None = None):
    rng = np.random.default_rng(seq + 100 * ACTORS.index(actor))
    d = obs_dim or st.spec.joint_obs_dim
    obs = rng.normal(size=(n, d)).astype(np.float32)
    return Transitions("r", actor, seq, obs=obs,
                       act=rng.uniform(size=(n, st.spec.joint_act_dim)).astype(np.float32),
                       rew=rng.normal(size=n).astype(np.float32), next_obs=obs,
                       done=np.zeros(n, np.float32), collisions=np.ones(n, np.int32),
                       policy_version=0)  # fmt: skip


def test_a_batch_waits_for_the_counters_ack_and_joins_replay_once(tmp_path):
    st = new_run(tmp_path)
    assert intake.take(st, batch(st, "a0", 0))
    assert len(st.intake.buffer) == 0 and len(st.intake.held["a0"]) == 1  # not counted yet
    assert not intake.take(st, batch(st, "a0", 0))  # a resend: not taken again
    assert not intake.take(st, batch(st, "a0", 2 * LEN))  # a gap: not taken
    st.intake.counted.ack("a0", LEN)
    intake.release_counted(st)
    assert len(st.intake.buffer) == LEN and not st.intake.held["a0"] and st.intake.ingested == LEN
    assert st.intake.received.positions() == {"a0": LEN, "a1": 0}
    assert [tuple(b) for b in st.intake.boundaries] == [(1, LEN - 3, LEN, LEN)]  # one episode


def test_an_arm_that_counts_nothing_takes_batches_into_replay_at_once(tmp_path):
    st = new_run(tmp_path, explore="constant")
    assert intake.take(st, batch(st, "a1", 0)) and len(st.intake.buffer) == LEN


def test_a_batch_of_another_length_or_layout_is_refused(tmp_path):
    st = new_run(tmp_path)
    with pytest.raises(WireError, match="one episode"):
        intake.take(st, batch(st, "a0", 0, n=LEN - 1))
    with pytest.raises(WireError, match="dims"):
        intake.take(st, batch(st, "a0", 0, obs_dim=3))
    assert st.intake.received.positions() == {"a0": 0, "a1": 0} and not st.intake.held["a0"]


def test_a_batch_that_cannot_be_logged_is_not_taken_and_its_resend_is(tmp_path):
    """Its log record is made before the cursor moves: taken first, a batch whose
    policy_version overflowed the log's int32 column was never logged, and its resend
    was a duplicate (decode refuses such a version now; this is the order behind it)."""
    st = new_run(tmp_path)
    ckpt.open_log(st)
    bad = dataclasses.replace(batch(st, "a0", 0), policy_version=2**31)
    with pytest.raises(OverflowError):
        intake.take(st, bad)
    assert st.intake.received.positions() == {"a0": 0, "a1": 0} and not st.intake.held["a0"]
    assert intake.take(st, batch(st, "a0", 0))  # the resend is taken, and logged
    st.intake.log.close()
    again = new_run(tmp_path)
    assert [(r.actor, r.seq) for r in ckpt.open_log(again)] == [("a0", 0)]
    again.intake.log.close()


def test_a_log_write_that_fails_takes_nothing_and_the_resend_is_taken(tmp_path):
    """A full disk (the log's append raising OSError) leaves the cursor where it was:
    moved first, the batch was in neither the log nor replay, and its resend a
    duplicate, while the next ack said the learner had it."""
    st = new_run(tmp_path)
    ckpt.open_log(st)
    log = st.intake.log
    real = log.append

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    log.append = full
    with pytest.raises(OSError):
        intake.take(st, batch(st, "a0", 0))
    assert st.intake.received.positions() == {"a0": 0, "a1": 0} and not st.intake.held["a0"]
    log.append = real
    assert intake.take(st, batch(st, "a0", 0))
    log.close()
    again = new_run(tmp_path)
    assert [(r.actor, r.seq) for r in ckpt.open_log(again)] == [("a0", 0)]
    again.intake.log.close()


def test_a_checkpoint_and_the_log_give_the_same_state_back(tmp_path):
    st = new_run(tmp_path)
    ckpt.open_log(st)
    for seq in (0, LEN):
        intake.take(st, batch(st, "a0", seq))
    st.intake.counted.ack("a0", LEN)
    intake.release_counted(st)  # the first episode is in replay, the second held
    ckpt.write(st)
    intake.take(st, batch(st, "a1", 0))  # taken after the cut: the log has it
    st.intake.log.close()

    again = new_run(tmp_path)
    records = ckpt.open_log(again)
    (path, state), *_ = list(ckpt.good(again, warn=print))
    assert path.name == ckpt.CUT
    again.learner.load_state_dict(state["learner"])
    assert ckpt.apply(again, state) == 1
    assert intake.replay(again, records)[0] == []
    assert len(again.intake.buffer) == len(st.intake.buffer) == LEN
    assert np.array_equal(again.intake.buffer.obs[:LEN], st.intake.buffer.obs[:LEN])
    held = again.intake.held
    assert [m.seq for m in held["a0"]] == [LEN] and [m.seq for m in held["a1"]] == [0]
    assert again.intake.received.positions() == st.intake.received.positions()
    assert again.sampling.rng.bit_generator.state == st.sampling.rng.bit_generator.state
    again.intake.log.close()


def test_a_cut_of_another_config_is_refused_naming_the_field(tmp_path):
    st = new_run(tmp_path)
    ckpt.write(st)
    other = new_run(tmp_path, explore="dis-macb")
    with pytest.raises(ckpt.CutError, match="explore"):
        list(ckpt.good(other, warn=print))


def test_a_lost_evaluation_point_is_sent_again_by_the_clock_alone():
    ev = EvaluationsInFlight()
    from tests.test_evaluator_order import _weights

    ev.unreported = {20: (100.0, _weights(20, [])), 40: (100.0, _weights(40, [20]))}
    ev.last_sent, ev.reported_at = 40, 100.0
    assert ev.due(104.0) == []  # the evaluator may just be busy
    assert [p for p, _ in ev.due(106.0)] == [20]  # it holds 40 for 20: 20 was lost
    assert [p for p, _ in ev.due(106.5, at_once=True)] == [20, 40]
