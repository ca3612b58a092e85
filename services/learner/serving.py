"""The runs a learner serves, one alone or a lockstep group's, and what a tick and each
inbound event do to them: updates (updates.py), weights and acks (outbound.py), cuts
(checkpoint.py), action answers (lockstep.py).

Bus-free: it sends only through the runs' publishers and its `Outbound`, so the service
(main.py) is the shell that opens runs on the bus, dispatches messages here and ends
runs (completed, stopped, failed) with their statuses.
"""

from __future__ import annotations

import logging
import time

from services.learner import checkpoint as ckpt
from services.learner import lockstep, updates
from services.learner.lockstep import LockstepGroup
from services.learner.outbound import Outbound
from services.learner.state import LearnerRun
from shared.config import TrainConfig
from shared.net import bus as keys
from shared.net.messages import ActRequest, Assignment


class Serving:
    """The learner's runs: `runs` (the run served, or a group's runs), `group`."""

    def __init__(self, out: Outbound, log: logging.Logger) -> None:
        self.out, self.log = out, log
        self.runs: dict[str, LearnerRun] = {}
        self.group: LockstepGroup | None = None
        self.gathering: dict[str, TrainConfig] = {}  # a group's runs whose start came

    @property
    def st(self) -> LearnerRun | None:
        """The run served alone (None when free or serving a group)."""
        return None if self.group is not None else next(iter(self.runs.values()), None)

    def gathered(self, run: str, config: TrainConfig, assign: Assignment) -> bool:
        """A group's run noted; True once every run of the group has its start."""
        if assign.group:
            self.gathering[run] = config
            return set(self.gathering) == set(assign.group)
        return False

    def group_of(self, run: str) -> list[str]:
        """The runs that end with `run`: its group's, or itself."""
        g = self.group
        return list(g.runs) if g is not None and run in g.runs else [run]

    def drop(self, run: str) -> None:
        """Forget a run's state (the group too, with its last run)."""
        self.runs.pop(run, None)
        self.gathering.pop(run, None)
        if self.group is not None and not any(r in self.runs for r in self.group.runs):
            self.group = None

    def finished(self) -> list[LearnerRun]:
        return [st for st in self.runs.values() if st.done]

    # ------------------------------------------------------------ ticks
    def tick(self) -> bool:
        """One tick of updates and what goes out after them; True if updates are owed
        at once (the service checks its inbox and comes back)."""
        if self.group is not None:
            self.group_tick(self.group)
            return False
        st = self.st
        return False if st is None else self.run_tick(st)

    def run_tick(self, st: LearnerRun) -> bool:
        updates.update_run(st, updates.updates_due(st))
        owed = st.owed_total - st.learner.updates
        self.out.boundaries(st)
        self.out.housekeep(st, owed)
        if ckpt.due(st) and not st.sampling.unpriced:
            self.checkpoint(st)  # (not with minibatches in hand: a cut holds the sampler)
        if st.lockstep and owed == 0:
            for actor, payload in lockstep.answers(st):
                st.asks.pubs[actor](payload)
        return owed > 0 and not st.done

    def group_tick(self, g: LockstepGroup) -> None:
        """The group trainer's step (cli/group_trainer.py) over the bus: once every
        run has taken (and counted) this step, each samples and prices its own
        minibatches and one GroupMADDPG update updates them all; then the group's next
        request is answered with one `act` for every run."""
        members = [self.runs[r] for r in g.runs if r in self.runs]
        if (
            len(members) == len(g.runs)
            and all(st.owed_total > g.learner.updates for st in members)
            and not updates.update_group(g, members)
        ):
            members = []  # the counter is silent: nothing more this tick
        for st in members:
            self.out.boundaries(st)
            self.out.housekeep(st, st.owed_total - g.learner.updates)
        if members and ckpt.due(members[0]) and not any(st.sampling.unpriced for st in members):
            for st in members:  # together: a group resumes from one update
                self.checkpoint(st)
        if (payload := lockstep.group_answer(g, self.runs)) is not None:
            g.action_pub(payload)

    def checkpoint(self, st: LearnerRun) -> None:
        """A cut of the run (checkpoint.py)."""
        if st.cuts.folder is not None:
            spent = ckpt.write(st)
            self.log.debug("run %s: cut at episode %d (%d bytes, %.1f ms)",
                           st.run, st.intake.episodes, st.cuts.size, 1e3 * spent)  # fmt: skip

    # ------------------------------------------------------------ events
    def act_request(self, st: LearnerRun, key: str, msg: ActRequest) -> str | None:
        """A step's request for actions, kept until it can be answered (the answer sent
        again if it was lost); the reason it is refused, if it is."""
        g = self.group
        if g is not None:
            if msg.actor != g.actor or keys.run_of(key) != g.runs[0]:
                return f"act_request from {msg.actor}: not this group's actor"
            if again := lockstep.take_group_request(g, st.spec.joint_obs_dim, msg):
                g.action_pub(again)  # the answer was lost: the same actions again
        elif not st.lockstep or msg.actor not in st.asks.pubs:
            return f"act_request from {msg.actor}: not a lockstep actor of this run"
        elif again := lockstep.take_request(st, msg):
            st.asks.pubs[msg.actor](again)  # the answer was lost: the same action again
        return None

    def peer_found(self, role: str, peer: str, evaluator: str | None) -> None:
        """A service of the run came back: an actor gets weights and where to go on, the
        evaluator the points it has not reported."""
        for st in list(self.runs.values()):
            if role == "actor" and peer in st.actors:
                self.out.weights(st, eval_point=-1)
                self.out.ack(st)
            elif role == "evaluator" and peer == evaluator:
                self.out.resend(st, time.monotonic(), at_once=True)

    def peer_lost(
        self, role: str, peer: str, evaluator: str | None, grace_s: float
    ) -> list[tuple[LearnerRun, str]]:
        """The runs a peer gone past the grace period fails, each with the reason: an
        actor's transitions, or the evaluator's rows, cannot come."""
        out = []
        for st in self.runs.values():
            if role == "evaluator" and peer == evaluator:
                out.append(
                    (st, f"evaluator {peer} died and did not come back within {grace_s:g} s")
                )
            elif role == "actor" and peer in st.actors and peer not in st.final:
                why = f"actor {peer} died before it finished its episodes"
                out.append((st, f"{why} (not back within {grace_s:g} s)"))
        return out
