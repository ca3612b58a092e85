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
each run's transition on that run's keys, numbered and resent as a run's are. A run
alone is served as a group of one: one code path for both (`runs.py`).

An actor restarted mid-run rejoins it (`on_resume`): it waits for the learner's ack,
which says how many of its transitions the learner holds, numbers on from there (what
it had in flight when it died is collected anew) and runs the rest of its episodes.

This module is the shell: the bus, the timers and the dispatch. The parts hold no bus:
`outbox.py` (numbering, resends, where a rejoin goes on), `lockstep.py` (the act
request and its answer) and `runs.py` (`ActorRuns`: the runs served, one alone or a
group's, their worlds and steps).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import torch

from services.actor.lockstep import valid_action
from services.actor.outbox import BadWorld, Outbox, rejoin_from, run_sender
from services.actor.runs import ActorRuns
from services.common import ServiceBase
from services.runs import LearnerProcesses
from shared.config import TrainConfig
from shared.core.networks import weights_error
from shared.net import bus as keys
from shared.net.messages import Ack, Action, Assignment, Weights
from shared.net.wire import WireError, decode

# Runs whose newest weights an actor keeps (it serves one at a time; the others are
# runs beside it on the bus, or over).
NEWEST_RUNS_KEPT = 16
STATS_EVERY_S = 1.0


def group_subs(runs: list[str]) -> str:
    """What the runs' shared subscription (the answers, on the lead run's keys) is held
    under: it outlives the lead run when its rule ends it before the others."""
    return f"group:{runs[0]}"


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
        # The learner processes whose weights this actor acted with, per run: a retry's
        # new learner's first weights may come after its start, and the ended attempt's,
        # still the newest kept, are not its.
        self.acted_with = LearnerProcesses(NEWEST_RUNS_KEPT)
        # Subscribed for the service's lifetime: the learner's first weights may be out
        # before this actor has handled the start message.
        self.bus.subscribe(keys.k_weights("*", "*"), self._on_weights)
        self.st: ActorRuns | None = None  # the runs served: one alone, or a group's
        self._members: dict[str, TrainConfig] = {}  # a group's runs whose start came
        self._retired: set[str] = set()  # of those, retired by their rule (a restart)

    def _on_weights(self, key: str, payload: bytes) -> None:
        run = keys.run_of(key)
        if run is None:
            return  # (subscribed on run keys: every key names its run)
        with self._newest_lock:  # Zenoh's threads
            newest = self._newest
            newest.pop(run, None)  # re-inserted: the order is then the order of arrival
            newest[run] = (key, payload)
            while len(newest) > NEWEST_RUNS_KEPT:  # runs long over
                newest.pop(next(iter(newest)))

    # ------------------------------------------------------------ lifecycle
    def outbox(self, run: str, config: TrainConfig, assign: Assignment) -> Outbox:
        """A run's outbox on the bus (its acks listened to; its publisher, as its
        subscriptions, ends when the run is freed)."""
        self.listen(keys.k_ack(run, "*"), "ack", run)
        sender = run_sender(config, assign)
        pub = self.endpoint.publisher(keys.k_transitions(run, self.id), run)
        return Outbox(run, self.id, sender, pub)

    def on_start(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        self._open(run, config, assign, rejoining=False)

    def on_resume(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        self._open(run, config, assign, rejoining=True)

    def _open(self, run: str, config: TrainConfig, assign: Assignment, rejoining: bool) -> None:
        """Once every run has its start (a run alone at once, a group's last run), their
        worlds; after a restart (`rejoining`) it first waits to hear where each run is."""
        runs = list(assign.group or [run])
        self._members = {r: c for r, c in self._members.items() if r in runs}  # (not others')
        self._members[run] = config
        if set(self._members) != set(runs):
            return
        cfgs = [self._members.pop(r) for r in runs]
        self.acted_with.begin(runs)
        retired, self._retired = self._retired & set(runs), set()
        outboxes = {r: self.outbox(r, cfg, assign) for r, cfg in zip(runs, cfgs)}
        act_pub = None
        if config.interleave == "lockstep":  # (a group's: on its lead run's keys; the
            # answers' subscription held by the group, as its lead may end before the others)
            act_pub = self.endpoint.publisher(keys.k_act(runs[0], self.id), group_subs(runs))
            self.listen(keys.k_action(runs[0], self.id), "action", group_subs(runs))
        actors = list(assign.actors)
        rank, grouped = actors.index(self.id), assign.group is not None
        self.st = st = ActorRuns.open(self.id, cfgs, outboxes, act_pub, rank, len(actors), grouped)
        st.stopped |= retired  # (their worlds step on, unpublished)
        for r in st.going:
            self.publish_status(r, "running", **self.running(st))
        if rejoining:
            st.rejoin = rejoin_from(assign, cfgs, time.monotonic())

    def running(self, st: ActorRuns) -> dict[str, Any]:
        """A run's "running" status: where the actor is among the run's actors."""
        return {"rank": st.rank, "episodes": st.todo, **({"group": st.runs} if st.grouped else {})}

    def on_resume_retired(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        """A run of the group its rule ended before this process restarted: its world
        steps with the others', its steps unpublished."""
        self._members[run] = config
        self._retired.add(run)

    def on_stop(self, run: str, reason: str) -> None:
        self._members.pop(run, None)
        if self.st is not None and run in self.st.runs:
            self.end_runs()  # (each run of a group is stopped: the others follow)

    def end_runs(self) -> None:
        """The runs served are over: their group's subscriptions end with them."""
        if self.st is not None:
            self.endpoint.drop_run(group_subs(self.st.runs))
            for run in self.st.stopped:  # (a retired run's acks, listened to after a restart)
                self.endpoint.drop_run(run)
        self.st = None

    # ------------------------------------------------------------ inbound
    def handle(self, tag: str, key: str, payload: bytes) -> None:
        if tag == "action":
            self.on_action(key, payload)
            return
        if tag != "ack":
            return
        msg = self.decode_for_run(key, payload, Ack)
        st = self.st
        if msg is None or st is None or msg.run not in st.outboxes:
            return
        acked = msg.acked.get(self.id)
        if st.rejoin is not None:
            st.rejoin.ack(msg.run, msg.service, acked)
            self.rejoin_if_known()
        st.outboxes[msg.run].sender.on_ack(msg.service, acked, time.monotonic(), window=msg.window)

    def on_action(self, key: str, payload: bytes) -> None:
        st = self.st
        if st is not None and st.stopped and st.runs[0] == keys.run_of(key):
            try:  # (the lead run ended by its rule: its keys still carry the answers)
                msg: Action | None = decode(payload, Action)
            except WireError as err:
                self.reject(key, str(err))
                return
            if msg is not None and msg.run != st.runs[0]:
                self.reject(key, "run mismatch: key and message name different runs")
                return
        else:
            msg = self.decode_for_run(key, payload, Action)
        if msg is None or st is None:
            return
        if not all(isinstance(r, str) and r in st.runs for r in msg.ended):
            self.reject(key, f"action: ended runs {msg.ended!r:.200} not of the group {st.runs}")
            return
        for run in msg.ended:  # (before stepping: their steps are not to be published)
            self.on_learner_completed(run)
        if self.st is not st or not st.exchange.awaits(msg.seq):
            return  # an answer to a request resent earlier, already taken
        if not valid_action(msg.act, st.act_shape):
            self.reject(key, f"action: shape {msg.act.shape} or non-finite values")
            return
        st.exchange.answer(msg.seq, msg.act)

    def rejoin_if_known(self) -> None:
        """Rejoining: go on once the positions are known (or the counter's wait is over)."""
        st = self.st
        if st is None or st.rejoin is None:
            return
        positions = st.rejoin.positions(st.going, time.monotonic())
        if positions is None:
            return
        position = st.rejoin_at(positions)
        runs = {"runs": st.runs} if st.grouped else {"run": st.runs[0]}
        self.resumed = {**runs, "from_transition": position, "episodes": st.done}
        self.log.info(
            "runs %s: rejoined at transition %d (%d of %d episodes done; %s)",
            st.runs, position, st.done, st.todo, positions,
        )  # fmt: skip
        for run in st.going:
            self.publish_status(run, "running", **self.running(st), rejoined_at=position)

    def load_newest_weights(self, st: ActorRuns) -> None:
        """Act with the run's newest weights message if its actors are newer. One refused
        (malformed, or actors not of this policy's layout, which raised in this loop and
        ended the process) is counted once and forgotten: the actor goes on with the
        weights it has, and the learner's next weights come at its next boundary."""
        run = st.runs[0]
        with self._newest_lock:
            newest = self._newest.get(run)
        if newest is None or newest is st.looked_at:
            return  # (each arrival is a new tuple: one looked at says the same again)
        st.looked_at = newest
        msg, why = self.decode_or_why(*newest, Weights)
        if msg is None:
            self._forget_newest(run, newest)  # (refused: counted once, not every tick)
            return
        if self.acted_with.of_ended_attempt(run, msg.incarnation) or not self.of_attempt(
            run, msg.attempt
        ):
            return  # (an ended attempt's: the new learner's first weights are to come)
        if not st.newer(msg):
            return
        if st.policy is not None and (bad := weights_error(msg.actors, st.policy.layout)):
            self.reject(newest[0], f"weights: {bad}")
            self._forget_newest(run, newest)
            return
        if st.load_weights(msg):
            self.acted_with.took(run, msg.incarnation)

    def _forget_newest(self, run: str, newest: tuple[str, bytes]) -> None:
        """Drop the run's newest weights message if it is still `newest` (newer ones may
        have come on Zenoh's thread meanwhile: those are kept)."""
        with self._newest_lock:
            if self._newest.get(run) is newest:
                del self._newest[run]

    # ------------------------------------------------------------ work
    def tick(self) -> bool:
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
        st.resend_due(now)
        if now - st.last_stats > STATS_EVERY_S:
            st.last_stats = now
            for run in st.going:
                self.publish_metrics(run, st.stats(run, sum(self.rejects.values())).to_wire())
        if st.finished:
            return self.finish_if_settled(st)
        try:
            if st.lockstep:  # one step of every world per answered act request
                return st.lockstep_step(now)
            if st.lead.sender.can_send(st.episode_len):
                st.run_episode()
                return True
        except BadWorld as err:  # (the group's worlds step together: all of it ends)
            self.log.error("%s", err)
            for run in list(self.active):
                self._end(run, "failed", str(err))
            return False
        return False

    def on_learner_completed(self, run: str) -> None:
        """The learner completed before this actor published its episodes (its status
        said so, or its answer to an act request named the run ended): the run's
        `early_stop` rule held at a point (a learner completes otherwise only once every
        share is in). In lockstep it holds each step after a point until the point's
        row is in, so everything published is taken: the run completes here. A group's
        other runs go on: its world still steps, its steps are no longer published."""
        st = self.st
        if st is None or run not in st.going or st.finished:
            return
        ending = [run] if len(st.going) > 1 else st.going  # (a group's others go on)
        for r in ending:
            stats = st.stats(r, sum(self.rejects.values())).to_wire()
            self.publish_metrics(r, stats)
            seq = st.outboxes[r].sender.seq
            self.publish_status(r, "completed", final_seq=seq, stopped_early=True, **stats)
        self.log.info("runs %s: the learner ended them by their rule after %d episodes",
                      ending, st.done)  # fmt: skip
        if ending == st.going:
            for r in ending:
                self.free(r)
            self.end_runs()
        else:
            self.retire(run)  # (noted: a restarted actor steps its world with the others')
            st.stopped.update(ending)

    def finish_if_settled(self, st: ActorRuns) -> bool:
        if st.settled:
            for run in st.going:
                stats = st.stats(run, sum(self.rejects.values())).to_wire()
                self.publish_metrics(run, stats)
                seq = st.outboxes[run].sender.seq
                self.publish_status(run, "completed", final_seq=seq, **stats)
                self.free(run)
            self.log.info("runs %s: %d episodes published", st.going, st.done)
            self.end_runs()
        return False


def make_service(service_id: str, connect: list[str], data_dir: Path) -> ActorService:
    return ActorService(service_id, connect, data_dir)
