"""The actor service: collects training episodes and publishes them, numbered, once each.

An actor of rank r (its place in the run's assignment) steps one environment
seeded from (run seed, "actor", r) and runs its share of the run's episodes. Each
episode goes out as one `transitions` batch stamped with the weights version that
acted. Weights arrive on a callback that only keeps the newest message; the actor
loads it between episodes, so it never works through a backlog of stale weights.

Every batch stays in a resend queue until the learner (and, when counting, the
counter) have acknowledged it, and is resent after a second without progress; the
learner's window of credits and a bound on batches the counter has not acknowledged
hold the actor back when either falls behind or is down (`shared.net.protocol.Sender`).

With `interleave: lockstep` (the thesis's loop over the bus) the actor steps once per
action the learner sends: it asks for the action at its next observation (`act_request`,
resent after ACT_RESEND_S without an answer), which the learner computes with its current
weights once every earlier step is counted and learnt, adds its own noise, steps and
publishes that one transition. Actions come from the learner's own network, so they are
the one-process trainer's to the bit (SEED RL's central inference).

A run group in lockstep (`assign["group"]`: its runs in order) has one actor for all its
runs: it steps their worlds as one VecTask (world r is run r's), asks for every run's
action in one request on the first run's keys, adds each run's own noise and publishes
each run's transition on that run's keys, numbered and resent as a run's are.

An actor restarted mid-run rejoins it (`on_resume`): it waits for the learner's ack,
which says how many of its transitions the learner holds, numbers on from there (what
it had in flight when it died is collected anew) and runs the rest of its episodes.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from services.common import ServiceBase
from shared.config import TrainConfig
from shared.core.networks import JointPolicy
from shared.envs.tasks import TaskEnv, make_task_for
from shared.envs.vectask import vectorize
from shared.net import bus as keys
from shared.net.messages import Ack, Action, ActRequest, Transitions, Weights
from shared.net.protocol import Rejoin, Sender, episode_share
from shared.net.wire import encode
from shared.run.rollout import Collector, VecCollector, make_collector, make_vec_collector

MAX_UNCOUNTED_BATCHES = 8  # episodes in flight that the counter has not acknowledged
RESEND_AFTER_S = 1.0
ACT_RESEND_S = 1.0  # lockstep: an act request with no answer is sent again
# Runs whose newest weights an actor keeps (it serves one at a time; the others are
# runs beside it on the bus, or over).
NEWEST_RUNS_KEPT = 16


@dataclass
class ActorRun:
    """Everything an actor holds for the run it serves."""

    rank: int
    env: TaskEnv
    collector: Collector
    policy: JointPolicy
    todo: int  # episodes this actor runs
    sender: Sender  # numbering, unacknowledged batches, resends, credit
    pub: Callable[[bytes], None]
    version: int = -1  # weights version acting now; -1 until the learner's first weights
    incarnation: Any = None  # the learner process whose weights those are
    rejoin: Rejoin | None = None  # restarted: waiting to hear where to go on
    done: int = 0
    steps: int = 0
    last_stats: float = 0.0
    t0: float = field(default_factory=time.perf_counter)
    lockstep: bool = False
    act_pub: Callable[[bytes], None] | None = None
    # lockstep: the open request's (seq, first sent, last sent)
    asked: tuple[int, float, float] | None = None
    action: tuple[int, np.ndarray] | None = None  # lockstep: the learner's answer
    act_wait_s: float = 0.0  # lockstep: time from a request to its answer


@dataclass
class GroupActor:
    """A lockstep group's worlds and, per run, its numbering and resends."""

    runs: list[str]
    cfgs: list[TrainConfig]
    collector: VecCollector
    senders: dict[str, Sender]
    pubs: dict[str, Callable[[bytes], None]]
    act_pub: Callable[[bytes], None]
    todo: int  # episodes (every run's)
    episode_len: int
    seq: int = 0  # steps taken (each run's transitions so far)
    done: int = 0
    asked: tuple[int, float, float] | None = None  # the open request: seq, first, last sent
    action: tuple[int, np.ndarray] | None = None  # the learner's answer: (R, joint_act)
    act_wait_s: float = 0.0
    last_stats: float = 0.0
    t0: float = field(default_factory=time.perf_counter)
    # restarted: the learner's position of each run, until it has said all of them
    rejoin: Rejoin | None = None


class ActorService(ServiceBase):
    role = "actor"
    follows_learner = True

    def __init__(self, service_id: str, connect: list[str] | None, data_dir: Path) -> None:
        super().__init__(service_id, connect, data_dir)
        torch.set_num_threads(1)
        # The newest weights message of each run (older versions are never looked at).
        # Per run: with several runs on the bus (`macb up --slots`) another run's weights,
        # published every episode, must not overwrite this run's first ones, which are
        # published once before any episode (an actor waited for them forever).
        self._newest: dict[str, tuple[str, bytes]] = {}
        self._newest_lock = threading.Lock()
        # Subscribed for the service's lifetime: the learner's first weights may be out
        # before this actor has handled the start message.
        self.bus.subscribe(keys.k_weights("*", "*"), self._on_weights)
        self.st: ActorRun | None = None
        self.ga: GroupActor | None = None  # a lockstep group's worlds, when serving one
        self._members: dict[str, TrainConfig] = {}  # a group's runs whose start came

    def _on_weights(self, key: str, payload: bytes) -> None:
        run = keys.run_of(key)
        with self._newest_lock:  # Zenoh's threads
            newest = self._newest
            newest.pop(run, None)  # re-inserted: the order is then the order of arrival
            newest[run] = (key, payload)
            while len(newest) > NEWEST_RUNS_KEPT:  # runs long over
                newest.pop(next(iter(newest)))

    # ------------------------------------------------------------ lifecycle
    def on_resume(self, run: str, config: TrainConfig, assign: dict[str, Any]) -> None:
        if assign.get("group"):
            self._members[run] = config
            if set(self._members) == set(assign["group"]):
                self.open_group(assign, rejoining=True)
            return
        self.on_start(run, config, assign)
        assert self.st is not None
        self.st.rejoin = self._rejoin_from(assign, [config])

    def _rejoin_from(self, assign: dict[str, Any], cfgs: list[TrainConfig]) -> Rejoin:
        counting = any(c.explore in ("dis-macb", "cen-macb") for c in cfgs)
        counter = assign.get("counter") if counting else None
        return Rejoin(assign.get("learner", ""), counter, since=time.monotonic())

    def _rejoin_at(self, position: int) -> None:
        """The learner and the counter hold `position` of our transitions (the least
        of theirs: `shared.net.protocol.Rejoin`): go on from there."""
        st, cfg = self.st, self.config
        assert st is not None and cfg is not None
        if not st.lockstep:  # whole episodes only (they always are)
            position -= position % cfg.episode_len
        st.sender.seq = position
        for svc in st.sender.acked:
            st.sender.acked[svc] = position
        st.done = position // cfg.episode_len
        st.collector = make_collector(
            cfg, st.env, st.rank, len(self.assign["actors"]), steps_done=position
        )
        st.rejoin = None
        self.resumed = {"run": self.run_id, "from_transition": position, "episodes": st.done}
        self.log.info(
            "run %s: rejoined at transition %d (%d of %d episodes done)",
            self.run_id,
            position,
            st.done,
            st.todo,
        )
        self.publish_status(
            self.run_id, "running", rank=st.rank, episodes=st.todo, rejoined_at=position
        )

    def on_start(self, run: str, config: TrainConfig, assign: dict[str, Any]) -> None:
        if assign.get("group"):
            self._members[run] = config
            if set(self._members) == set(assign["group"]):
                self.open_group(assign)
            return
        actors = list(assign["actors"])
        rank = actors.index(self.id)
        self.listen(keys.k_ack(run, "*"), "ack", run)
        env = make_task_for(config)
        self.st = ActorRun(
            rank=rank,
            env=env,
            collector=make_collector(config, env, rank, len(actors)),
            policy=JointPolicy.for_task(env.spec, config.hidden),
            todo=episode_share(config.episodes, len(actors), rank),
            sender=run_sender(config, assign),
            pub=self.bus.publisher(keys.k_transitions(run, self.id)),
        )
        if config.interleave == "lockstep":
            self.st.lockstep = True
            self.st.act_pub = self.bus.publisher(keys.k_act(run, self.id))
            self.listen(keys.k_action(run, self.id), "action", run)
        self.publish_status(run, "running", rank=rank, episodes=self.st.todo)

    def open_group(self, assign: dict[str, Any], rejoining: bool = False) -> None:
        """Every run of the group has its start: their worlds as one VecTask. After a
        restart (`rejoining`) it first waits to hear where each run is."""
        runs = list(assign["group"])
        cfgs = [self._members.pop(run) for run in runs]
        senders = {run: run_sender(cfg, assign) for run, cfg in zip(runs, cfgs)}
        for run in runs:
            self.listen(keys.k_ack(run, "*"), "ack", run)
        venv = vectorize([make_task_for(cfg) for cfg in cfgs])
        lead = runs[0]
        self.ga = GroupActor(
            runs=runs,
            cfgs=cfgs,
            collector=make_vec_collector(cfgs, venv),
            senders=senders,
            pubs={run: self.bus.publisher(keys.k_transitions(run, self.id)) for run in runs},
            act_pub=self.bus.publisher(keys.k_act(lead, self.id)),
            todo=cfgs[0].episodes,
            episode_len=cfgs[0].episode_len,
        )
        self.listen(keys.k_action(lead, self.id), "action", lead)
        if rejoining:
            self.ga.rejoin = self._rejoin_from(assign, cfgs)
            return
        for run in runs:
            self.publish_status(run, "running", rank=0, episodes=self.ga.todo, group=runs)

    def group_rejoin_at(self, ga: GroupActor, positions: dict[str, int]) -> None:
        """The learner and the counter hold `positions` of each run's transitions (the
        least of theirs: `shared.net.protocol.Rejoin`): every world goes on from the least
        (a run ahead by a step gets that step again, which the learner and the counter
        take as a duplicate), with randomness of its own for the rest, as a restarted
        single actor does."""
        position = min(positions.values())
        ga.collector = make_vec_collector(ga.cfgs, ga.collector.venv, steps_done=position)
        for sender in ga.senders.values():
            sender.seq = position
            for svc in sender.acked:
                sender.acked[svc] = position
        ga.seq, ga.done = position, position // ga.episode_len
        ga.rejoin = ga.asked = ga.action = None
        self.resumed = {"runs": ga.runs, "from_transition": position, "episodes": ga.done}
        self.log.info("group %s: rejoined at transition %d (%s)", ga.runs, position, positions)
        for run in ga.runs:
            self.publish_status(
                run, "running", rank=0, episodes=ga.todo, group=ga.runs, rejoined_at=position
            )

    def on_stop(self, run: str, reason: str) -> None:
        self.st = None
        self._members.pop(run, None)
        if self.ga is not None and run in self.ga.runs:
            self.ga = None  # (each run of the group is stopped: the others follow)

    # ------------------------------------------------------------ inbound
    def handle(self, tag: str, key: str, payload: bytes) -> None:
        if tag == "action":
            self.on_action(key, payload)
            return
        if tag != "ack":
            return
        msg = self.decode_for_run(key, payload, Ack)
        ga = self.ga
        if msg is not None and ga is not None and msg.run in ga.senders:
            if ga.rejoin is not None:
                ga.rejoin.ack(msg.run, msg.service, msg.acked.get(self.id))
                self.rejoin_if_known()
                return
            sender = ga.senders[msg.run]
            sender.on_ack(msg.service, msg.acked.get(self.id), time.monotonic(), window=msg.window)
            return
        if msg is None or self.st is None:
            return
        if self.st.rejoin is not None:
            self.st.rejoin.ack(msg.run, msg.service, msg.acked.get(self.id))
            self.rejoin_if_known()
        self.st.sender.on_ack(
            msg.service, msg.acked.get(self.id), time.monotonic(), window=msg.window
        )

    def rejoin_if_known(self) -> None:
        """Rejoining: go on once the positions are known (or the counter's wait is over)."""
        now = time.monotonic()
        if self.ga is not None and self.ga.rejoin is not None:
            positions = self.ga.rejoin.positions(self.ga.runs, now)
            if positions is not None:
                self.group_rejoin_at(self.ga, positions)
        elif self.st is not None and self.st.rejoin is not None and self.run_id:
            positions = self.st.rejoin.positions([self.run_id], now)
            if positions is not None:
                self._rejoin_at(positions[self.run_id])

    def load_newest_weights(self) -> None:
        st = self.st
        newest = self._newest.get(self.run_id) if st is not None else None
        if newest is None:
            return
        key, payload = newest
        msg = self.decode_for_run(key, payload, Weights)
        if msg is None:
            return
        # A restarted learner numbers its versions on from its last cut: its weights are
        # newer than any of the process before, whatever their number.
        incarnation = msg.incarnation
        if msg.version > st.version or incarnation != st.incarnation:
            st.policy.load(msg.actors)
            st.version = msg.version
            st.incarnation = incarnation

    def on_action(self, key: str, payload: bytes) -> None:
        msg = self.decode_for_run(key, payload, Action)
        ga = self.ga
        if ga is not None:
            if msg is None or ga.asked is None or msg.seq != ga.asked[0]:
                return
            act = msg.act
            if act.shape != (len(ga.runs), len(ga.collector.low)) or not np.isfinite(act).all():
                self.reject(key, f"action: shape {act.shape} or non-finite values")
                return
            ga.action = (msg.seq, act.astype(np.float32, copy=False))
            return
        st = self.st
        if msg is None or st is None or st.asked is None or msg.seq != st.asked[0]:
            return  # an answer to a request resent earlier, already taken
        act = msg.act
        if act.shape != st.collector.low.shape or not np.isfinite(act).all():
            self.reject(key, f"action: shape {act.shape} or non-finite values")
            return
        st.action = (msg.seq, act.astype(np.float32, copy=False))

    # ------------------------------------------------------------ work
    def tick(self) -> bool:
        if self.ga is not None:
            return self.group_tick(self.ga)
        st = self.st
        if st is None:
            return False
        if st.lockstep:
            return self.lockstep_tick()
        self.load_newest_weights()
        if st.rejoin is not None:
            self.rejoin_if_known()
            return False  # rejoining: wait for the acks that say where to go on
        if st.version < 0:
            return False  # wait for the learner's weights
        self.resend_and_report(time.monotonic())
        if st.done < st.todo:
            if st.sender.can_send(self.config.episode_len):
                self.run_episode()
                return True
            return False
        return self.finish_if_settled()

    def lockstep_tick(self) -> bool:
        """One step per answered act request; a request for the next step goes out at
        once (the learner answers it after learning this one)."""
        st = self.st
        assert st is not None and st.act_pub is not None
        if st.rejoin is not None:
            self.rejoin_if_known()
            return False
        now = time.monotonic()
        self.resend_and_report(now)
        if st.done >= st.todo:
            return self.finish_if_settled()
        seq = st.sender.seq
        if st.action is not None and st.asked is not None and st.action[0] == seq:
            act = st.action[1]
            st.act_wait_s += now - st.asked[1]
            st.action = st.asked = None
            self.publish_steps([st.collector.step(lambda obs: act[None])])
            st.steps += 1
            if st.sender.seq % self.config.episode_len == 0:
                st.done += 1
            if st.done >= st.todo:
                return True
            seq = st.sender.seq
        if st.asked is None or now - st.asked[2] > ACT_RESEND_S:
            obs = st.collector.next_obs()
            st.act_pub(encode(ActRequest(self.run_id, actor=self.id, seq=seq, obs=obs)))
            st.asked = (seq, now if st.asked is None else st.asked[1], now)
        return False

    def group_tick(self, ga: GroupActor) -> bool:
        """`lockstep_tick` for a group: one step of every run's world per answer."""
        if ga.rejoin is not None:
            self.rejoin_if_known()
            return False
        now = time.monotonic()
        for run, sender in ga.senders.items():
            for payload in sender.due(now):
                ga.pubs[run](payload)
        if now - ga.last_stats > 1.0:
            ga.last_stats = now
            for run in ga.runs:
                self.publish_metrics(run, self.group_stats(ga, run))
        if ga.done >= ga.todo:
            if all(s.settled for s in ga.senders.values()):
                for run in ga.runs:
                    stats = self.group_stats(ga, run)
                    self.publish_metrics(run, stats)
                    self.publish_status(run, "completed", final_seq=ga.seq, **stats)
                    self.free(run)
                self.log.info("group %s: %d episodes published", ga.runs, ga.done)
                self.ga = None
            return False
        if ga.action is not None and ga.asked is not None and ga.action[0] == ga.seq:
            act = ga.action[1]
            ga.act_wait_s += now - ga.asked[1]
            ga.action = ga.asked = None
            tr = ga.collector.step(lambda obs: act[:, None])
            for r, run in enumerate(ga.runs):
                payload = transitions_payload(
                    run, self.id, ga.seq, tr.obs[r : r + 1], tr.act[r : r + 1],
                    tr.rew[r : r + 1], tr.next_obs[r : r + 1], tr.done[r : r + 1],
                    tr.collisions[r : r + 1], -1,
                )  # fmt: skip
                ga.senders[run].send(1, payload, now)
                ga.pubs[run](payload)
            ga.seq += 1
            if ga.seq % ga.episode_len == 0:
                ga.done += 1
            if ga.done >= ga.todo:
                return True
        if ga.asked is None or now - ga.asked[2] > ACT_RESEND_S:
            obs = ga.collector.next_obs()
            lead = ga.runs[0]
            ga.act_pub(encode(ActRequest(lead, actor=self.id, seq=ga.seq, obs=obs)))
            ga.asked = (ga.seq, now if ga.asked is None else ga.asked[1], now)
        return False

    def group_stats(self, ga: GroupActor, run: str) -> dict[str, Any]:
        wall = time.perf_counter() - ga.t0
        sender = ga.senders[run]
        return {
            "rank": 0,
            "episodes": ga.done,
            "published": sender.seq,
            "policy_version": -1,
            "resends": sender.resends,
            "steps_per_sec": ga.seq / wall if wall > 0 else 0.0,
            "rejects_total": sum(self.rejects.values()),
            "act_wait_ms": 1e3 * ga.act_wait_s / ga.seq if ga.seq else 0.0,
            "group": len(ga.runs),
        }

    def resend_and_report(self, now: float) -> None:
        """Batches due for a resend go out again; stats once a second."""
        st = self.st
        assert st is not None
        for payload in st.sender.due(now):
            st.pub(payload)
        if now - st.last_stats > 1.0:
            st.last_stats = now
            self.publish_metrics(self.run_id, self.stats())

    def finish_if_settled(self) -> bool:
        st = self.st
        assert st is not None
        if st.sender.settled:
            run = self.run_id
            self.publish_metrics(run, self.stats())
            self.publish_status(run, "completed", final_seq=st.sender.seq, **self.stats())
            self.log.info("run %s: %d episodes published", run, st.done)
            self.st = None
            self.free(run)
        return False

    def publish_steps(self, rows: list) -> None:
        """Publish transitions as one numbered batch (resent until acknowledged)."""
        st = self.st
        assert st is not None
        payload = transitions_payload(
            self.run_id, self.id, st.sender.seq,
            np.stack([t.obs for t in rows]), np.stack([t.act for t in rows]),
            np.array([t.rew for t in rows]), np.stack([t.next_obs for t in rows]),
            np.array([t.done for t in rows]), np.array([t.collisions for t in rows]),
            st.version,
        )  # fmt: skip
        st.sender.send(len(rows), payload, time.monotonic())
        st.pub(payload)

    def run_episode(self) -> None:
        st = self.st
        assert st is not None
        collector, policy = st.collector, st.policy
        rows = [collector.step(policy) for _ in range(self.config.episode_len)]
        self.publish_steps(rows)
        st.done += 1
        st.steps += len(rows)

    def stats(self) -> dict[str, Any]:
        st = self.st
        assert st is not None
        wall = time.perf_counter() - st.t0
        return {
            "rank": st.rank,
            "episodes": st.done,
            "published": st.sender.seq,
            "policy_version": st.version,
            "resends": st.sender.resends,
            "steps_per_sec": st.steps / wall if wall > 0 else 0.0,
            "rejects_total": sum(self.rejects.values()),
            # lockstep: mean time from an act request to its action (the learner's
            # update, the count before it and the bus's round trips)
            "act_wait_ms": 1e3 * st.act_wait_s / st.steps if st.lockstep and st.steps else 0.0,
        }


def run_sender(config: TrainConfig, assign: dict[str, Any]) -> Sender:
    """A run's numbering, resends and credit: confirmed by its learner and, when it
    counts, its counter (which also bounds what may be in flight uncounted)."""
    learner, counter = assign.get("learner"), assign.get("counter")
    counting = config.explore in ("dis-macb", "cen-macb")
    return Sender(
        confirm=(learner, counter) if counting else (learner,),
        credit_from=learner,
        bounded=(counter,) if counting else (),
        max_unconfirmed=MAX_UNCOUNTED_BATCHES,
        resend_after_s=RESEND_AFTER_S,
        last_progress=time.monotonic(),
    )


def transitions_payload(
    run: str, actor: str, seq: int, obs, act, rew, next_obs, done, collisions, version: int
) -> bytes:
    """One numbered `transitions` batch (rows seq, seq+1, ...) as the wire carries it."""
    return encode(
        Transitions(
            run,
            actor=actor,
            seq=seq,
            obs=np.asarray(obs, np.float32),
            act=np.asarray(act, np.float32),
            rew=np.asarray(rew, np.float32),
            next_obs=np.asarray(next_obs, np.float32),
            done=np.asarray(done, np.float32),
            collisions=np.asarray(collisions, np.int32),
            policy_version=version,
        )
    )


def make_service(service_id: str, connect: list[str], data_dir: Path) -> ActorService:
    return ActorService(service_id, connect, data_dir)
