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

A run group in lockstep (`assign.group`: its runs in order) has one actor for all its
runs: it steps their worlds as one VecTask (world r is run r's), asks for every run's
action in one request on the first run's keys, adds each run's own noise and publishes
each run's transition on that run's keys, numbered and resent as a run's are.

An actor restarted mid-run rejoins it (`on_resume`): it waits for the learner's ack,
which says how many of its transitions the learner holds, numbers on from there (what
it had in flight when it died is collected anew) and runs the rest of its episodes.

This module is the shell: the bus, the timers and the dispatch. The parts hold no bus:
`outbox.py` (numbering, resends, where a rejoin goes on), `lockstep.py` (the act
request and its answer), `run.py` (`ActorRun`: a run's world and steps) and `group.py`
(`GroupActor`: a lockstep group's worlds as one VecTask).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import torch

from services.actor.group import GroupActor
from services.actor.lockstep import valid_action
from services.actor.outbox import Outbox, rejoin_from, run_sender
from services.actor.run import ActorRun
from services.common import ServiceBase
from shared.config import TrainConfig
from shared.net import bus as keys
from shared.net.messages import Ack, Action, Assignment, Weights

# Runs whose newest weights an actor keeps (it serves one at a time; the others are
# runs beside it on the bus, or over).
NEWEST_RUNS_KEPT = 16
STATS_EVERY_S = 1.0


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
    def outbox(self, run: str, config: TrainConfig, assign: Assignment) -> Outbox:
        """A run's outbox on the bus (its acks listened to)."""
        self.listen(keys.k_ack(run, "*"), "ack", run)
        sender = run_sender(config, assign)
        return Outbox(run, self.id, sender, self.bus.publisher(keys.k_transitions(run, self.id)))

    def on_start(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        if assign.group:
            self._members[run] = config
            if set(self._members) == set(assign.group):
                self.open_group(assign)
            return
        actors = list(assign.actors)
        rank = actors.index(self.id)
        outbox = self.outbox(run, config, assign)
        act_pub = None
        if config.interleave == "lockstep":
            act_pub = self.bus.publisher(keys.k_act(run, self.id))
            self.listen(keys.k_action(run, self.id), "action", run)
        self.st = ActorRun.open(config, rank, len(actors), outbox, act_pub)
        self.publish_status(run, "running", rank=rank, episodes=self.st.todo)

    def on_resume(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        if assign.group:
            self._members[run] = config
            if set(self._members) == set(assign.group):
                self.open_group(assign, rejoining=True)
            return
        self.on_start(run, config, assign)
        assert self.st is not None
        self.st.rejoin = rejoin_from(assign, [config], time.monotonic())

    def open_group(self, assign: Assignment, rejoining: bool = False) -> None:
        """Every run of the group has its start: their worlds as one VecTask. After a
        restart (`rejoining`) it first waits to hear where each run is."""
        runs = list(assign.group or ())
        cfgs = [self._members.pop(run) for run in runs]
        outboxes = {run: self.outbox(run, cfg, assign) for run, cfg in zip(runs, cfgs)}
        lead = runs[0]
        act_pub = self.bus.publisher(keys.k_act(lead, self.id))
        self.ga = GroupActor.open(self.id, cfgs, outboxes, act_pub)
        self.listen(keys.k_action(lead, self.id), "action", lead)
        if rejoining:
            self.ga.rejoin = rejoin_from(assign, cfgs, time.monotonic())
            return
        for run in runs:
            self.publish_status(run, "running", rank=0, episodes=self.ga.todo, group=runs)

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
        if msg is not None and ga is not None and msg.run in ga.outboxes:
            if ga.rejoin is not None:
                ga.rejoin.ack(msg.run, msg.service, msg.acked.get(self.id))
                self.rejoin_if_known()
                return
            sender = ga.outboxes[msg.run].sender
            sender.on_ack(msg.service, msg.acked.get(self.id), time.monotonic(), window=msg.window)
            return
        if msg is None or self.st is None:
            return
        if self.st.rejoin is not None:
            self.st.rejoin.ack(msg.run, msg.service, msg.acked.get(self.id))
            self.rejoin_if_known()
        self.st.outbox.sender.on_ack(
            msg.service, msg.acked.get(self.id), time.monotonic(), window=msg.window
        )

    def on_action(self, key: str, payload: bytes) -> None:
        msg = self.decode_for_run(key, payload, Action)
        part = self.ga if self.ga is not None else self.st
        if msg is None or part is None or not part.exchange.awaits(msg.seq):
            return  # an answer to a request resent earlier, already taken
        if not valid_action(msg.act, part.act_shape):
            self.reject(key, f"action: shape {msg.act.shape} or non-finite values")
            return
        part.exchange.answer(msg.seq, msg.act)

    def rejoin_if_known(self) -> None:
        """Rejoining: go on once the positions are known (or the counter's wait is over)."""
        now = time.monotonic()
        ga, st = self.ga, self.st
        if ga is not None and ga.rejoin is not None:
            positions = ga.rejoin.positions(ga.runs, now)
            if positions is not None:
                self.group_rejoined(ga, positions)
        elif st is not None and st.rejoin is not None and self.run_id:
            positions = st.rejoin.positions([self.run_id], now)
            if positions is not None:
                self.rejoined(st, positions[self.run_id])

    def rejoined(self, st: ActorRun, position: int) -> None:
        run, position = st.outbox.run, st.rejoin_at(position)
        self.resumed = {"run": run, "from_transition": position, "episodes": st.done}
        self.log.info(
            "run %s: rejoined at transition %d (%d of %d episodes done)",
            run, position, st.done, st.todo,
        )  # fmt: skip
        self.publish_status(run, "running", rank=st.rank, episodes=st.todo, rejoined_at=position)

    def group_rejoined(self, ga: GroupActor, positions: dict[str, int]) -> None:
        position = ga.rejoin_at(positions)
        self.resumed = {"runs": ga.runs, "from_transition": position, "episodes": ga.done}
        self.log.info("group %s: rejoined at transition %d (%s)", ga.runs, position, positions)
        for run in ga.runs:
            status = {"rank": 0, "episodes": ga.todo, "group": ga.runs, "rejoined_at": position}
            self.publish_status(run, "running", **status)

    def load_newest_weights(self, st: ActorRun) -> None:
        newest = self._newest.get(st.outbox.run)
        if newest is not None:
            msg = self.decode_for_run(*newest, Weights)
            if msg is not None:
                st.load_weights(msg)

    # ------------------------------------------------------------ work
    def tick(self) -> bool:
        if self.ga is not None:
            return self.group_tick(self.ga)
        st = self.st
        if st is None:
            return False
        if not st.lockstep:
            self.load_newest_weights(st)
        if st.rejoin is not None:
            self.rejoin_if_known()
            return False  # rejoining: wait for the acks that say where to go on
        if not st.lockstep and st.version < 0:
            return False  # wait for the learner's weights
        now = time.monotonic()
        st.outbox.resend_due(now)
        if now - st.last_stats > STATS_EVERY_S:
            st.last_stats = now
            self.publish_metrics(st.outbox.run, st.stats(sum(self.rejects.values())))
        if st.done >= st.todo:
            return self.finish_if_settled(st)
        if st.lockstep:  # one step per answered act request
            return st.lockstep_step(now)
        if st.outbox.sender.can_send(st.config.episode_len):
            st.run_episode()
            return True
        return False

    def group_tick(self, ga: GroupActor) -> bool:
        """A lockstep tick for a group: one step of every run's world per answer."""
        if ga.rejoin is not None:
            self.rejoin_if_known()
            return False
        now = time.monotonic()
        ga.resend_due(now)
        if now - ga.last_stats > STATS_EVERY_S:
            ga.last_stats = now
            for run in ga.runs:
                self.publish_metrics(run, ga.stats(run, sum(self.rejects.values())))
        if not ga.finished:
            return ga.step(now)
        if ga.settled:
            for run in ga.runs:
                stats = ga.stats(run, sum(self.rejects.values()))
                self.publish_metrics(run, stats)
                self.publish_status(run, "completed", final_seq=ga.seq, **stats)
                self.free(run)
            self.log.info("group %s: %d episodes published", ga.runs, ga.done)
            self.ga = None
        return False

    def finish_if_settled(self, st: ActorRun) -> bool:
        if st.outbox.sender.settled:
            run = st.outbox.run
            stats = st.stats(sum(self.rejects.values()))
            self.publish_metrics(run, stats)
            self.publish_status(run, "completed", final_seq=st.outbox.sender.seq, **stats)
            self.log.info("run %s: %d episodes published", run, st.done)
            self.st = None
            self.free(run)
        return False


def make_service(service_id: str, connect: list[str], data_dir: Path) -> ActorService:
    return ActorService(service_id, connect, data_dir)
