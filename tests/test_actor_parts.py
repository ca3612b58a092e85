"""The actor service's parts in process, no bus: the lockstep handshake, the outbox's
numbering, resends and rejoin position, a run's steps and weights, a group's steps
(`ActorRuns`: a run alone is a group of one)."""

from __future__ import annotations

import numpy as np

from services.actor.lockstep import ACT_RESEND_S, ActExchange, valid_action
from services.actor.outbox import RESEND_AFTER_S, Outbox, rejoin_from, run_sender
from services.actor.runs import ActorRuns
from shared.config import make_config
from shared.envs.tasks import make_task_for
from shared.net.messages import ActRequest, Assignment, Transitions, Weights
from shared.net.wire import decode
from shared.run.rollout import make_collector

ASSIGN = Assignment.from_wire({"learner": "learner", "counter": "counter", "actors": ["a0"]})
BASE = {"task": "speaker_listener", "episodes": 3, "episode_len": 5, "hidden": [16, 16]}


def config(**extra):
    return make_config({**BASE, **extra})


def outbox(cfg, run: str = "r") -> tuple[Outbox, list[bytes]]:
    sent: list[bytes] = []
    return Outbox(run, "a0", run_sender(cfg, ASSIGN), sent.append), sent


def alone(cfg, box: Outbox, act_pub=None) -> ActorRuns:  # noqa: ANN001
    """A run alone: rank 0 of one actor."""
    return ActorRuns.open("a0", [cfg], {box.run: box}, act_pub)


# ------------------------------------------------------------ the handshake
def test_a_request_goes_out_once_then_again_only_after_the_resend_wait():
    ex = ActExchange()
    assert ex.ask(0, now=10.0)
    assert not ex.ask(0, now=10.0 + ACT_RESEND_S)  # still within the wait
    assert ex.ask(0, now=10.0 + ACT_RESEND_S + 0.1)
    assert ex.asked == (0, 10.0, 10.0 + ACT_RESEND_S + 0.1)  # keeps its first sending


def test_only_the_open_requests_answer_is_taken_and_its_wait_counted():
    ex = ActExchange()
    assert not ex.awaits(0)  # nothing asked: any answer is stale
    ex.ask(3, now=1.0)
    assert ex.awaits(3) and not ex.awaits(2)
    ex.answer(3, np.ones(2, np.float64))
    assert ex.take(4, now=1.5) is None  # not the step it was asked for
    act = ex.take(3, now=1.5)
    assert act is not None and act.dtype == np.float32 and ex.wait_s == 0.5
    assert ex.asked is None and ex.take(3, now=2.0) is None  # taken once
    ex.ask(4, now=3.0)
    ex.forget()
    assert ex.asked is None and ex.ask(4, now=3.0)


def test_an_answer_of_another_shape_or_not_finite_is_not_stepped_with():
    assert valid_action(np.zeros((2, 3)), (2, 3))
    assert not valid_action(np.zeros(3), (2, 3))
    assert not valid_action(np.array([[0.0, np.nan, 0.0], [0, 0, 0]]), (2, 3))


# ------------------------------------------------------------ the outbox
def test_batches_are_numbered_kept_until_both_acks_and_resent_without_progress():
    cfg = config(explore="dis-macb")
    box, sent = outbox(cfg)
    n = 5
    cols = (np.zeros((n, 4)), np.zeros((n, 2)), np.zeros(n), np.zeros((n, 4)), np.zeros(n),
            np.zeros(n, np.int32))  # fmt: skip
    box.publish(*cols, version=7, now=100.0)
    box.publish(*cols, version=8, now=100.0)
    msgs = [decode(p, Transitions) for p in sent]
    assert [(m.seq, len(m), m.policy_version, m.actor) for m in msgs] == [
        (0, 5, 7, "a0"),
        (5, 5, 8, "a0"),
    ]
    box.resend_due(100.0 + RESEND_AFTER_S / 2)
    assert len(sent) == 2  # not yet
    box.resend_due(100.0 + RESEND_AFTER_S + 0.1)
    assert sent[2:] == sent[:2]  # both again, in order
    box.sender.on_ack("learner", 10, now=102.0)
    assert not box.sender.settled  # the counter has not counted them
    box.sender.on_ack("counter", 10, now=102.0)
    assert box.sender.settled


def test_a_run_that_counts_nothing_waits_for_the_learner_alone():
    cfg = config(explore="none")
    assert tuple(run_sender(cfg, ASSIGN).confirm) == ("learner",)
    assert rejoin_from(ASSIGN, [cfg], now=0.0).counter is None
    counting = config(explore="dis-macb")
    assert rejoin_from(ASSIGN, [cfg, counting], now=0.0).counter == "counter"


# ------------------------------------------------------------ a run
def test_weights_are_loaded_when_newer_or_from_another_learner_process():
    class Policy:
        loads: list = []

        def load(self, actors) -> None:
            self.loads.append(actors)

    st = alone(config(), outbox(config())[0])
    st.policy = Policy()

    def weights(version: int, incarnation: str) -> Weights:
        return Weights("r", version=version, updates=0, env_steps=0, episodes=0, eval_point=-1,
                       collisions_cum=0, actors=[], stats={}, incarnation=incarnation)  # fmt: skip

    assert st.load_weights(weights(3, "l1")) and st.version == 3
    assert not st.load_weights(weights(3, "l1")) and not st.load_weights(weights(2, "l1"))
    assert st.load_weights(weights(1, "l2"))  # a restarted learner: newer whatever its number
    assert (st.version, st.incarnation, len(Policy.loads)) == (1, "l2", 2)


def test_an_episode_goes_out_as_one_batch_stamped_with_the_version():
    cfg = config()
    box, sent = outbox(cfg)
    st = alone(cfg, box)
    st.version = 4
    st.run_episode()
    (msg,) = [decode(p, Transitions) for p in sent]
    assert (msg.seq, len(msg), msg.policy_version) == (0, cfg.episode_len, 4)
    assert (st.done, st.steps, box.sender.seq) == (1, cfg.episode_len, cfg.episode_len)


def test_lockstep_steps_with_the_learners_actions_as_the_collector_would():
    cfg = config(interleave="lockstep")
    box, sent = outbox(cfg)
    asked: list[bytes] = []
    st = alone(cfg, box, act_pub=asked.append)
    twin = make_collector(cfg, make_task_for(cfg))  # the same seeds: the same world
    assert not st.lockstep_step(now=0.0)  # no answer yet: asks for step 0
    req = decode(asked[0], ActRequest)
    assert (req.seq, req.actor) == (0, "a0")
    assert np.array_equal(req.obs, twin.next_obs())
    rng = np.random.default_rng(0)
    for step in range(cfg.episode_len * st.todo):
        act = rng.uniform(-1, 1, st.act_shape).astype(np.float32)
        st.exchange.answer(step, act)
        last = st.lockstep_step(now=float(step))
        want = twin.step(lambda obs, act=act: act[None])
        got = decode(sent[-1], Transitions)
        assert got.seq == step and np.array_equal(got.act[0], want.act)
        assert np.array_equal(got.next_obs[0], want.next_obs)
        if last:
            break
        assert decode(asked[-1], ActRequest).seq == step + 1  # the next request at once
    assert last and st.done == st.todo == cfg.episodes


def test_a_rejoin_goes_on_from_whole_episodes_async_and_from_the_step_in_lockstep():
    cfg = config()
    st = alone(cfg, outbox(cfg)[0])
    assert st.rejoin_at({"r": 12}) == 10  # episodes of 5: the one begun is collected anew
    assert (st.lead.sender.seq, st.done) == (10, 2)
    assert set(st.lead.sender.acked.values()) == {10}
    cfg = config(interleave="lockstep")
    st = alone(cfg, outbox(cfg)[0], act_pub=[].append)
    assert st.rejoin_at({"r": 12}) == 12 and st.done == 2


# ------------------------------------------------------------ a group
def group(n: int = 2) -> tuple[ActorRuns, dict[str, list[bytes]], list[bytes]]:
    cfgs = [config(interleave="lockstep", seed=s) for s in range(n)]
    boxes = {f"r{i}": outbox(c, f"r{i}") for i, c in enumerate(cfgs)}
    asked: list[bytes] = []
    outboxes = {r: b for r, (b, _) in boxes.items()}
    ga = ActorRuns.open("a0", cfgs, outboxes, asked.append, grouped=True)
    return ga, {r: s for r, (_, s) in boxes.items()}, asked


def test_a_group_asks_once_for_every_run_and_publishes_each_runs_step_on_its_keys():
    ga, sent, asked = group()
    assert not ga.lockstep_step(now=0.0)
    req = decode(asked[0], ActRequest)
    assert req.run == "r0" and req.seq == 0 and req.obs.shape[0] == 2  # the lead's keys
    act = np.zeros(ga.act_shape, np.float32)
    ga.exchange.answer(0, act)
    assert not ga.lockstep_step(now=0.5)
    for run in ("r0", "r1"):
        (msg,) = [decode(p, Transitions) for p in sent[run]]
        assert (msg.run, msg.seq, len(msg), msg.policy_version) == (run, 0, 1, -1)
    assert ga.lead.sender.seq == 1 and decode(asked[-1], ActRequest).seq == 1
    assert not ga.settled
    for box in ga.outboxes.values():
        box.sender.on_ack("learner", 1, now=1.0)
        box.sender.on_ack("counter", 1, now=1.0)
    assert ga.settled


def test_a_group_rejoins_every_world_at_the_least_position():
    ga, _, _ = group()
    ga.exchange.ask(0, now=0.0)
    assert ga.rejoin_at({"r0": 11, "r1": 10}) == 10
    assert (ga.lead.sender.seq, ga.done, ga.exchange.asked) == (10, 2, None)
    assert {box.sender.seq for box in ga.outboxes.values()} == {10}
