"""The learner service's parts in process, no bus: the update loop at the replay ratio
(updates.py), when a lockstep request is answered (lockstep.py), what goes out at an
episode's end and between updates (outbound.py), a group's resume from the newest
update all its runs have a cut of (checkpoint.py), and which counter's bonus reply is
taken (bonus.py)."""

from __future__ import annotations

import logging
import time
import types

import numpy as np
import pytest

from services.learner import checkpoint as ckpt
from services.learner import intake, lockstep, updates
from services.learner.bonus import BonusClient, bus_query
from services.learner.evaluations import EvaluationsInFlight, reported_point
from services.learner.outbound import MAX_BACKLOG_EPISODES, Outbound
from services.learner.state import LearnerRun, RunGroup, new_run
from shared.config import make_config
from shared.core.learners.runs import SoloRuns
from shared.envs.tasks import task_spec_for
from shared.net.bus import Refused, Replies
from shared.net.messages import (
    Ack,
    Action,
    ActRequest,
    BonusQuery,
    BonusReply,
    Metrics,
    Weights,
)
from shared.net.wire import WireError, decode, encode
from shared.run.factories import build_learner
from tests.test_learner_intake import batch

LEN = 5
ACTORS = ["a0", "a1"]


class Sent(list):
    """A publisher that records what it was given, decoded as `cls`."""

    def __init__(self, cls: type) -> None:
        super().__init__()
        self.cls = cls

    def __call__(self, payload: bytes) -> None:
        self.append(decode(payload, self.cls))


class SilentCounter:
    """A bus whose counter never answers a bonus query (paused, restarting)."""

    def get_async(self, key, payload, timeout):  # noqa: ANN001, ARG002
        return None

    def collect_all(self, replies):  # noqa: ANN001, ARG002
        return Replies()

    def reject(self, key, why):  # noqa: ANN001, ARG002
        pass


def run(tmp_path, explore="constant", interleave="async", svc=None, attempt=None, **extra):  # noqa: ANN001
    cfg = make_config({"task": "speaker_listener", "explore": explore, "episodes": 8,
                       "episode_len": LEN, "hidden": [16, 16], "learning_starts": 3,
                       "learner_lanes": 1, "eval_every": 2, "interleave": interleave,
                       **extra})  # fmt: skip
    spec = task_spec_for(cfg)
    folder = tmp_path / "learner" / "r"
    folder.mkdir(parents=True, exist_ok=True)
    bonus = BonusClient(bus_query(svc, "bonus"), print, "r", cfg.explore, cfg.beta,
                        spec.n_agents)  # fmt: skip
    pubs = {"weights": Sent(Weights), "eval": Sent(Weights), "ack": Sent(Ack)}
    return new_run("r", cfg, spec, ACTORS, learner=build_learner(cfg, spec), bonus=bonus,
                   evaluations=EvaluationsInFlight(), pubs=pubs, counter="c",
                   folder=folder, attempt=attempt)  # fmt: skip


def alone(st: LearnerRun, asks: lockstep.Asks | None = None) -> RunGroup:
    """The run served alone: a group of one."""
    return RunGroup([st.run], SoloRuns(st.learner), asks=asks)


def update_run(st: LearnerRun, todo: int) -> int:
    return updates.update(alone(st), [st], todo)


def outbound(metrics=None) -> Outbound:  # noqa: ANN001
    return Outbound("l", metrics or (lambda *a, **k: None), lambda: 0, lambda c: [],
                    logging.getLogger("test"))  # fmt: skip


def fill(st, actor="a0", episodes=1):  # noqa: ANN001
    for e in range(episodes):
        assert intake.take(st, batch(st, actor, e * LEN))  # an arm that counts nothing


def test_a_tick_does_the_updates_owed_up_to_the_episodes_end_and_no_more(tmp_path):
    st = run(tmp_path)
    fill(st, episodes=2)  # 10 transitions, 3 of warm-up: 7 updates owed
    assert st.owed_total == 7 and [b.updates for b in st.intake.boundaries] == [2, 7]
    assert updates.updates_due(st) == 2  # the first episode's end comes first
    assert update_run(st, updates.updates_due(st)) == 2 and st.learner.updates == 2
    assert updates.updates_due(st) == 0  # its weights go out before more updates
    outbound().boundaries(st)
    assert update_run(st, updates.updates_due(st)) == 5 and st.learner.updates == 7
    assert updates.updates_due(st) == 0


def test_minibatches_a_silent_counter_left_unpriced_are_priced_later_not_redrawn(tmp_path):
    st = run(tmp_path, explore="dis-macb", svc=SilentCounter())
    fill(st)
    intake.counter_acked(st, {"a0": LEN})
    sp = st.sampling
    state = dict(sp.rng.bit_generator.state)
    assert update_run(st, 2) == 0 and st.learner.updates == 0
    drawn = sp.unpriced
    assert len(drawn) == 2 and sp.rng.bit_generator.state != state
    after = dict(sp.rng.bit_generator.state)
    assert update_run(st, 2) == 0  # still silent: the same two, nothing drawn
    assert sp.unpriced is drawn and sp.rng.bit_generator.state == after
    # counted as unanswered, not as failed (a reply that is there and unusable)
    assert (st.bonus.unanswered, st.bonus.failures) == (2, 0)
    st.bonus.mode = "constant"  # the counter answers (priced here, for the test)
    assert update_run(st, 2) == 2 and not sp.unpriced
    assert sp.rng.bit_generator.state == after  # priced, not redrawn


def test_weights_go_out_at_each_episode_end_and_every_eval_every_to_the_evaluator(tmp_path):
    st, out = run(tmp_path), outbound()
    fill(st, episodes=2)
    update_run(st, 7)
    out.boundaries(st)
    sent = st.outgoing
    assert [(w.episodes, w.eval_point) for w in sent.weights_pub] == [(1, -1)]
    assert [(w.episodes, w.eval_point, w.version) for w in sent.eval_pub] == [(2, 2, 2)]
    assert set(st.evaluations.unreported) == {2}  # kept until the evaluator's row comes
    assert sent.eval_pub[0].stats["updates"] == 7


def test_the_credit_window_closes_while_the_learner_is_behind_and_reopens(tmp_path):
    st, rows = run(tmp_path), []
    out = outbound(lambda run, data, source: rows.append(source))
    behind = MAX_BACKLOG_EPISODES * LEN * len(ACTORS)
    sent = st.outgoing
    out.housekeep(st, behind)
    assert sent.ack_pub[-1].window == 0 and not sent.window_open
    out.housekeep(st, behind - 1)
    assert sent.ack_pub[-1].window > 0 and sent.window_open
    assert len(sent.weights_pub) == 1  # nothing taken yet: the first weights again
    assert rows == ["learner"]


def test_an_ack_names_the_attempt_of_the_run(tmp_path):
    """(An actor of another attempt of the run drops it: acks only move forward.)"""
    st = run(tmp_path, attempt=3)
    outbound().ack(st)
    assert st.outgoing.ack_pub[-1].attempt == 3


def test_a_lockstep_request_is_answered_only_once_its_steps_are_in_replay_and_learnt(tmp_path):
    st = run(tmp_path, interleave="lockstep")
    obs, dim = np.zeros(st.spec.joint_obs_dim, np.float32), st.spec.joint_obs_dim
    g, runs = alone(st, lockstep.Asks("a0", print)), {"r": st}
    assert lockstep.take_request(g, dim, ActRequest("r", "a0", seq=1, obs=obs)) is None
    assert lockstep.answer(g, runs) is None  # step 0 is not in replay
    it = st.intake
    it.received.take("a0", 0, 1)
    it.ingested_pos["a0"], it.ingested = 1, 4  # step 0 of a0 in; one update owed (warm-up 3)
    b = batch(st, "a0", 0)
    it.buffer.add(b.obs, b.act, b.rew, b.next_obs, b.done)  # (rows to sample from)
    assert lockstep.answer(g, runs) is None  # its update is not done
    update_run(st, 1)
    payload = lockstep.answer(g, runs)
    assert payload is not None and decode(payload, Action).seq == 1
    again = lockstep.take_request(g, dim, ActRequest("r", "a0", seq=1, obs=obs))
    assert again == payload  # the answer was lost: the same one again
    with pytest.raises(WireError, match="obs"):
        lockstep.take_request(g, dim, ActRequest("r", "a0", seq=2, obs=obs[:3]))


def test_a_group_resumes_from_the_newest_update_every_run_has_a_cut_of(tmp_path):
    sts = [run(tmp_path / str(r)) for r in range(2)]
    written = {0: [], 1: []}
    for u in (2, 4):
        for r, st in enumerate(sts):
            if u == 4 and r == 1:
                continue  # killed between the two runs' files
            st.learner.updates = u
            st.intake.episodes = u
            ckpt.write(st)
            written[r].append(u)
    loaded = []
    group = types.SimpleNamespace(load_run_state_dicts=loaded.extend)
    fresh = [run(tmp_path / str(r)) for r in range(2)]
    assert ckpt.restore(group, fresh, print) == [2, 2]
    assert len(loaded) == 2 and [st.intake.episodes for st in fresh] == [2, 2]


def test_an_evaluators_row_names_its_point_or_is_refused():
    assert reported_point(encode(Metrics("r", source="eval", data={"episode": 40}))) == 40
    with pytest.raises(WireError, match="episode"):
        reported_point(encode(Metrics("r", source="eval", data={"episode": True})))
    with pytest.raises(WireError):
        reported_point(encode(Metrics("r", source="eval", data={})))


# ------------------------------------------------------------ rows on Zenoh's thread
def test_a_row_reported_while_a_resend_is_encoded_is_not_undone(monkeypatch):
    """`due` re-encodes a point's weights (milliseconds) while Zenoh's thread may report
    its row: it once wrote its snapshot back, and the point reported was unreported
    again (sent again, and the run held for its row)."""
    from services.learner import evaluations as module
    from tests.test_evaluator_order import _weights

    ev = EvaluationsInFlight()
    ev.unreported = {20: (100.0, _weights(20, [])), 40: (100.0, _weights(40, [20]))}
    ev.last_sent, ev.reported_at = 40, 100.0
    encode_again = module.with_unreported

    def row_meanwhile(payload: bytes, earlier: list[int]) -> bytes:
        ev.reported(decode(payload, Weights).eval_point)  # (Zenoh's thread, mid-encode)
        return encode_again(payload, earlier)

    monkeypatch.setattr(module, "with_unreported", row_meanwhile)
    assert ev.due(200.0, at_once=True) == []  # both reported while re-encoded: none sent
    assert ev.unreported == {} and ev.last_reported == 40


def test_rows_and_resends_on_two_threads_leave_every_point_reported():
    """Rows come on Zenoh's thread while the learner's resends: iterating the points as
    a row removed one raised 'dictionary changed size during iteration', and a resend
    wrote back points reported meanwhile."""
    import sys
    import threading

    from tests.test_evaluator_order import _weights

    ev = EvaluationsInFlight()
    points = range(0, 400, 2)
    ev.unreported = {p: (0.0, _weights(p, [])) for p in points}  # (sent, then lost)
    errors: list[BaseException] = []
    reporting = threading.Event()

    def learner() -> None:
        try:
            while not reporting.is_set():
                ev.due(1e9, at_once=True)
        except BaseException as err:  # noqa: BLE001 (the test reports it)
            errors.append(err)

    def zenoh() -> None:
        for p in reversed(points):  # (the earliest last: every resend names them)
            ev.reported(p)
            time.sleep(0)  # (the learner's turn)
        reporting.set()

    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # switch threads as often as it can
    try:
        threads = [threading.Thread(target=f, daemon=True) for f in (learner, zenoh)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=120)
    finally:
        sys.setswitchinterval(switch)
    assert errors == [] and ev.unreported == {} and ev.reported_rows == len(points)


@pytest.mark.parametrize(
    "data", [{"episode": 4, "env_steps": "x", "success_rate": 0.5},
             {"episode": 4, "env_steps": float("inf"), "success_rate": 0.5},  # (OverflowError)
             {"episode": 4}],
)  # fmt: skip
def test_a_row_early_stop_cannot_read_is_counted_on_the_services_thread(data):
    """A malformed `early_stop` row raised on Zenoh's thread, uncounted (the reading was
    outside the try): it goes to the inbox as a reject, and the point stays unreported."""
    import queue
    import threading

    from services.inbox import Rejects
    from services.learner.main import LearnerService
    from services.runs import ServedRuns

    svc = LearnerService.__new__(LearnerService)
    svc.inbox, svc.log = queue.Queue(), logging.getLogger("test.learner")
    svc.served = ServedRuns(1, None, svc.log)
    svc.reject_tally, svc._traced, svc._traced_lock = Rejects(), set(), threading.Lock()
    ev = EvaluationsInFlight(early_stop=True)
    ev.sent(4, b"weights")
    svc.on_eval_row("r", ev, "macb/run/r/metrics/eval", encode(Metrics("r", "eval", data)))
    tag, key, why = svc.inbox.get_nowait()
    assert (tag, key) == ("reject", "macb/run/r/metrics/eval")
    assert why.startswith(b"metrics: eval row of point 4")
    assert 4 in ev.unreported and not ev.rows_in and ev.reported_rows == 0


class Counters:
    """Every counter's answers to the next query: (service, bonus) replies and refusals
    (by), as the run's key gets them; what was asked, decoded."""

    def __init__(self) -> None:
        self.next: tuple[list[tuple[str | None, np.ndarray]], list[str]] = ([], [])
        self.asked: list[BonusQuery] = []

    def get_async(self, key, payload, timeout):  # noqa: ANN001, ARG002
        self.asked.append(decode(payload, BonusQuery))
        replies, refusals = self.next
        ok = [
            encode(BonusReply("r", counts=np.ones((1, len(b)), np.int64), bonus=b, service=by))
            for by, b in replies
        ]
        return Replies(ok, [Refused(by, "no") for by in refusals])

    def collect_all(self, replies):  # noqa: ANN001
        return replies


def test_only_the_runs_counters_bonus_is_taken_and_only_a_finite_one(tmp_path):
    """Every counter answers the run's key: one that restored this run's tables of an
    ended attempt from disk answers too (a retry counted by another counter). Its
    reply, first or alone, is not the run's price; nor is a bonus not finite or < 0."""
    counters, rejects = Counters(), []
    client = BonusClient(bus_query(counters, "bonus"), rejects.append, "r", "cen-macb", 0.8,
                         2, counter="c1", attempt=2)  # fmt: skip
    b = batch(run(tmp_path), "a0", 0)
    stale, fresh = np.full((LEN, 2), 0.8, np.float32), np.full((LEN, 2), 0.1, np.float32)

    counters.next = ([("c0", stale), ("c1", fresh)], [])
    assert np.array_equal(client.bonus_for([b])[0], fresh)
    assert counters.asked[-1].attempt == 2  # (a counter of another attempt refuses it)
    counters.next = ([("c0", stale)], ["c1"])  # its own counter refused: a refusal
    assert client.bonus_for([b]) is None and client.refused == 1
    counters.next = ([("c0", stale)], [])  # its own counter silent: unanswered
    assert client.bonus_for([b]) is None and client.unanswered == 1
    assert client.failures == 0
    assert len(rejects) == 3 and all("another counter: c0, not c1" in r for r in rejects)

    for bad in (np.nan, np.inf, -0.5):
        counters.next = ([("c1", np.full((LEN, 2), bad, np.float32))], [])
        assert client.bonus_for([b]) is None
    assert client.failures == 3 and rejects[-1] == "bonus_reply: a bonus not finite and >= 0"
    counters.next = ([(None, fresh)], [])  # an older counter names none: taken
    assert np.array_equal(client.bonus_for([b])[0], fresh)
    assert client.queries == 2


def test_weights_gone_to_nan_fail_the_run_instead_of_going_out(tmp_path):
    """Actors and the evaluator refuse non-finite weights (they would act and evaluate
    on nothing): a learner gone to NaN raises `Diverged` before anything goes out, and
    the service fails the run saying so, rather than waiting for rows that never come."""
    from services.learner.outbound import Diverged

    st = run(tmp_path)
    out = outbound()
    out.weights(st, eval_point=2)
    assert len(st.outgoing.eval_pub) == 1  # finite: it went out
    weights = st.learner.actor_weights

    def gone_to_nan() -> list[dict]:
        sds = [{k: v.clone() for k, v in sd.items()} for sd in weights()]
        next(iter(sds[0].values())).fill_(float("nan"))
        return sds

    st.learner.actor_weights = gone_to_nan
    with pytest.raises(Diverged, match="run r: its learner's weights are not finite"):
        out.weights(st, eval_point=4)
    assert len(st.outgoing.eval_pub) == 1 and 4 not in st.evaluations.unreported
