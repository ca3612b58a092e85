"""The runs a learner serves as one (a `RunGroup`: a run alone is a group of one, a
lockstep group's runs share one learner), and what a tick and each inbound event do
to them: updates (updates.py), weights and acks (outbound.py), cuts (checkpoint.py),
action answers (lockstep.py).

Bus-free: it sends only through the runs' publishers and its `Outbound`, so the service
(main.py) is the shell that opens runs on the bus, dispatches messages here and ends
runs (completed, stopped, failed) with their statuses.
"""

from __future__ import annotations

import logging
import time

from services.learner import checkpoint as ckpt
from services.learner import lockstep, updates
from services.learner.outbound import Outbound
from services.learner.state import LearnerRun, RunGroup
from shared.config import TrainConfig
from shared.core.replay import fixed_update_arrays
from shared.net import bus as keys
from shared.net.messages import ActRequest, Assignment
from shared.persist import checkpoint


class Serving:
    """The learner's runs: `runs` (the run served, or a group's runs), `group` (them as
    one, with their learner)."""

    def __init__(self, out: Outbound, log: logging.Logger) -> None:
        self.out, self.log = out, log
        self.runs: dict[str, LearnerRun] = {}
        self.group: RunGroup | None = None
        self.gathering: dict[str, TrainConfig] = {}  # runs whose start came, before all
        self.retiring: set[str] = set()  # of those, retired by their rule (a restart)

    def gathered(self, run: str, config: TrainConfig, assign: Assignment) -> bool:
        """A run's start noted; True once every run served with it has its start (a run
        alone at once, a group's last run)."""
        runs = assign.group or [run]
        self.gathering = {r: c for r, c in self.gathering.items() if r in runs}  # (not others')
        self.gathering[run] = config
        return set(self.gathering) == set(runs)

    def group_of(self, run: str) -> list[str]:
        """The runs that end with `run`: its group's (a run alone's: itself)."""
        g = self.group
        return list(g.runs) if g is not None and run in g.runs else [run]

    def drop(self, run: str) -> None:
        """Forget a run's state (the group too, with its last run)."""
        self.runs.pop(run, None)
        self.gathering.pop(run, None)
        if self.group is not None and not any(r in self.runs for r in self.group.runs):
            self.group = None

    def goes_on_without(self, st: LearnerRun) -> bool:
        """`st` ends by its `early_stop` rule while other runs of its group go on."""
        g = self.group
        return (
            g is not None
            and g.grouped
            and st.stopped is not None
            and any(r != st.run and r in self.runs for r in g.runs)
        )

    def retire(self, st: LearnerRun) -> None:
        """A group's run ended by its rule, the others going on (as the one-process
        group does, cli/trainer.py `stop_member`): its state is let go, its stack entry
        runs on one fixed minibatch of its own (the update keeps its shape; entries do
        not mix, so the others' rows are what they give alone) and its world's steps are
        no longer asked for (lockstep.ready)."""
        g = self.group
        assert g is not None
        cfg = st.config
        arrays = fixed_update_arrays(
            st.intake.buffer, cfg.batch_size, st.sampling.per_update, st.spec.n_agents
        )
        g.retired[g.runs.index(st.run)] = arrays
        if st.cuts.folder is not None:  # (a restarted learner serves the group with it)
            ckpt.save_retired(st.cuts.folder, arrays)
        self.runs.pop(st.run, None)

    def finished(self) -> list[LearnerRun]:
        return [st for st in self.runs.values() if st.done]

    # ------------------------------------------------------------ ticks
    def tick(self) -> bool:
        """The trainer's step over the bus (cli/trainer.py, cli/trainer.py): once
        every run has taken (and counted) its transitions, the updates they owe (each run
        samples and prices its own minibatches, one learner update updates them all, at
        most to the next episode boundary), what goes out after them, a cut when due
        (every run's at once: a group resumes from one update), then the open act
        request answered. True if updates are owed at once (the service checks its
        inbox and comes back)."""
        g = self.group
        members = [self.runs[r] for r in g.runs if r in self.runs] if g is not None else []
        if g is None or not members:
            return False
        whole = len(members) + len(g.retired) == len(g.runs)
        for st in members:
            early_stop(st)
        updates.update(g, members, min(map(updates.updates_due, members)) if whole else 0)
        for st in members:
            self.out.boundaries(st)
            self.out.housekeep(st, st.owed_total - st.learner.updates)
        if ckpt.due(members[0]) and not any(st.sampling.unpriced for st in members):
            for st in members:  # (not with minibatches in hand: a cut holds the sampler)
                self.checkpoint(st)
        if g.asks is not None and (payload := lockstep.answer(g, self.runs)) is not None:
            g.asks.action_pub(payload)
        # (not while a group's run waits for another's step: nothing would be done)
        return whole and min(map(updates.updates_due, members)) > 0

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
        asks = g.asks if g is not None else None
        if g is None or asks is None or msg.actor != asks.actor or keys.run_of(key) != g.runs[0]:
            return f"act_request: not from the lockstep actor of these runs ({msg.actor:.40})"
        if again := lockstep.take_request(g, st.spec.joint_obs_dim, msg):
            asks.action_pub(again)  # the answer was lost: the same actions again
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


def early_stop(st: LearnerRun) -> None:
    """`early_stop` (lockstep): each point's row as it comes, in order. A point with a
    higher success than any before (the earliest of equals) has its learner written to
    best.pt, as `macb train` writes it; a row whose evaluator found the rule holding
    there stops the run at that point. Lockstep holds the next step until each point's
    row is read here, so the learner is the point's and nothing was taken after it."""
    rows = st.evaluations.rows_in
    while rows and st.stopped is None:
        row = rows.popleft()
        if row.success_rate > st.best and st.cuts.folder is not None:
            st.best = row.success_rate
            path = st.cuts.folder / checkpoint.BEST
            config = st.config.model_dump(mode="json")
            checkpoint.save_best(path, config, st.learner.state_dict(), row.as_row())
        if row.stop_reason is not None:
            st.stopped = (row.episode, row.stop_reason)
