"""The learner service: replay, updates at the thesis's replay ratio, weights, checkpoints.

A batch joins the replay buffer once the counter has acknowledged it (so every sampled
transition has been counted, n >= 1) and only once (`shared.net.protocol.ReceiveCursor`).
Exactly one update per ingested transition beyond `learning_starts`; actors get a
window of credits that closes while the learner is behind, so they wait rather than
let the ratio drift.

Bonuses are priced at sample time, one query per tick: a tick samples the minibatches
of all the updates it will do (up to UPDATES_PER_TICK, never past an episode boundary)
and asks the counter for their rows at once. Inbound messages are handled only
between ticks, so these are the minibatches per-update sampling would draw. One round
trip per tick instead of per update (docs/performance.md, "Learner service"); the
loop is updates.py.

Weights go out at every episode boundary (once its updates are done), marked
`eval_point` every `eval_every` episodes. While the evaluator evaluates weights this
learner sent (`EvaluationsInFlight`), updates are marked contended so the thread tuner
can pick what is fastest beside it. An evaluation point the evaluator has not reported
is sent again (a restarted evaluator, a restarted router), and the store keeps one row
per point (outbound.py: what goes out when).

With `interleave: lockstep` the thesis's loop runs over the bus (central inference, as
SEED RL does it): the one actor sends each step's observation (`act_request`) and one
transition per step; the learner answers a request with `learner.act` of its current
weights only when every earlier step has been counted, taken into replay and learnt
(its update done, priced with counts that include it). The run's updates, counts,
weights and evaluation points are then those of `macb train` with the same config
(lockstep.py: when a request can be answered).

Resume (docs/reliability.md, "The cluster"): every batch taken is appended to the
run's log `DATA_DIR/learner/RUN/transitions.wal` before it is acknowledged (intake.py),
and every CHECKPOINT_EVERY_S a cut (`checkpoint.pt`: networks, optimizers, targets,
update and episode counters, the sampler's RNG, which logged batches the buffer holds,
the episode boundaries still owed) is written atomically (checkpoint.py). A learner
restarted with the same id and data dir loads the newest good cut, refills the buffer
from the log and holds the logged batches beyond the cut until the counter's ack
covers them, as on first arrival: nothing the counter counted is missing from
replay, and the updates owed for those batches are done again.
"""

from __future__ import annotations

import json
import time
from collections.abc import Collection
from pathlib import Path
from typing import Any

import torch

from services.common import ServiceBase
from services.learner import checkpoint as ckpt
from services.learner import intake
from services.learner.bonus import BonusClient, bus_query
from services.learner.evaluations import EvaluationsInFlight, reported_row
from services.learner.lockstep import Asks
from services.learner.outbound import Diverged, Outbound
from services.learner.serving import Serving
from services.learner.state import LearnerRun, MemberLearner, RunGroup, new_run, open_error
from shared.config import TrainConfig
from shared.core.learners.group import GroupMADDPG
from shared.core.learners.runs import RunsLearner, SoloRuns
from shared.envs.tasks import task_spec_for
from shared.groups import group_error
from shared.net import bus as keys
from shared.net.messages import (
    MESSAGES,
    Ack,
    ActRequest,
    Assignment,
    Message,
    Resumed,
    Status,
    Transitions,
    new_incarnation,
)
from shared.net.wire import WireError, decode
from shared.persist import provenance
from shared.run.factories import agent_dims, build_learner, learner_spec


class LearnerService(ServiceBase):
    """The shell: runs opened on the bus (their keys, publishers, log and cut), messages
    dispatched to `Serving`, runs ended with their statuses."""

    role = "learner"

    def __init__(self, service_id: str, connect: list[str] | None, data_dir: Path) -> None:
        super().__init__(service_id, connect, data_dir)
        self.out = Outbound(
            self.id,
            self.publish_metrics,
            lambda: sum(self.rejects.values()),
            lambda counter: self.bus.get(keys.k_info("counter", counter), timeout=1.0),
            self.log,
        )
        self.serving = Serving(self.out, self.log)
        self.runs = self.serving.runs  # the run served, or a group's runs
        self.resume: Resumed | None = None  # what the start of the runs served resumed

    # ------------------------------------------------------------ run lifecycle
    def on_start(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        self._open(run, config, assign, resume=False)

    def on_resume_retired(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        """A run of the group its rule ended before this process restarted: its place in
        the group (its fixed update arrays), gathered with the others' starts."""
        self.serving.gathering[run] = config
        self.serving.retiring.add(run)

    def on_resume(self, run: str, config: TrainConfig, assign: Assignment) -> None:
        """Restarted mid-run: the newest good cut, then the log beyond it (module doc)."""
        self._open(run, config, assign, resume=True)

    def _open(self, run: str, config: TrainConfig, assign: Assignment, resume: bool) -> None:
        """The runs served as one, once every run has its start (a run alone at once, a
        group's last run): one learner for them all (a group's GroupMADDPG, run r of
        `assign.group` member r; a run alone's own, as a group of one), each run's own
        intake, replay, sampler, bonus queries, boundaries, evaluation points and cuts;
        resumed from the newest update every run has a cut of, then each run's log."""
        if not self.serving.gathered(run, config, assign):
            return
        t0, runs, grouped = time.perf_counter(), list(assign.group or [run]), bool(assign.group)
        retired = self.serving.retiring & set(runs)  # (resumed with the rest of the group)
        self.serving.retiring -= retired
        try:
            configs = [self.serving.gathering.pop(r) for r in runs]
            if grouped and (why := group_error(configs, len(assign.actors))):
                raise ValueError(why)
            for r in runs if not resume else []:
                ckpt.wipe(self.data_dir / "learner" / r)
            sts = self._open_runs(runs, configs, assign, retired)
            logs = [ckpt.open_log(st) for st in sts]
            cuts: list[int | None] = [None] * len(sts)
            if resume and self.serving.group is not None:
                slots = ([runs.index(st.run) for st in sts], len(runs)) if retired else None
                cuts = ckpt.restore(self.serving.group.learner, sts, self.log.warning, slots)
            for st, records in zip(sts, logs):
                if resume and st.config.early_stop is not None:
                    st.best = ckpt.best_so_far(st)
                skipped, newest = intake.replay(st, records)
                st.outgoing.version_at_least(newest)
                for batch in skipped:
                    self.log.warning("run %s: logged batch %s out of order: skipped", run, batch)
        except Exception as err:
            self.log.exception("runs %s failed to %s", runs, "resume" if resume else "start")
            self.fail_runs(f"{type(err).__name__}: {err}", runs)
            return
        infos = [ckpt.resumed(st, cut, time.perf_counter() - t0) for st, cut in zip(sts, cuts)]
        # what this start resumed (a group's: its lead run's, naming its runs)
        self.resume = (infos[0].grouped(runs) if grouped else infos[0]) if resume else None
        if self.resume is not None:
            self.resumed = self.resume.to_wire()
        for info in infos if resume else []:
            self.log.info("run %s resumed: %s", info.run, json.dumps(info.to_wire()))
        self.log.info("runs %s %s", runs, "resumed" if resume else "started")
        for st, info in zip(sts, infos):
            if not grouped:  # version 0: every actor starts from these (a group's acts by request)
                self.out.weights(st, eval_point=-1)
            detail: dict[str, Any] = {"group": runs} if grouped else {}
            resumed = info if resume else None
            self.publish_status(st.run, "running", resumed=resumed, actors=st.actors, **detail)
            self.publish_provenance(st)
            if resume:
                self.out.ack(st)  # the actors go on from what the log holds

    def _open_runs(
        self,
        runs: list[str],
        configs: list[TrainConfig],
        assign: Assignment,
        retired: Collection[str] = (),
    ) -> list[LearnerRun]:
        """The runs' states and their one learner; in lockstep, their one actor's act
        requests, on the lead run's keys (run 0). `retired`: runs of the group their rule
        ended before this learner restarted (their fixed update arrays, no state)."""
        for config in configs:
            if why := open_error(config, len(assign.actors)):
                raise ValueError(why)  # the run fails, saying so (not a silent change)
        spec, c0, grouped = task_spec_for(configs[0]), configs[0], bool(assign.group)
        torch.set_num_threads(c0.threads)
        evaluations = [EvaluationsInFlight(early_stop=c.early_stop is not None) for c in configs]
        learner: RunsLearner
        if grouped:
            specs = [learner_spec(c) for c in configs]
            learner = GroupMADDPG(agent_dims(spec), specs, precision=c0.precision, device=c0.device)
        else:
            learner = SoloRuns(build_learner(c0, spec, contended=evaluations[0].busy))
        group = RunGroup(runs, learner, grouped)
        if c0.interleave == "lockstep":  # (held by the group: its lead may end first)
            actor, lead = assign.actors[0], runs[0]
            answers = self.endpoint.publisher(keys.k_action(lead, actor), group.subs)
            group.asks = Asks(actor, answers)
            self.listen(keys.k_act(lead, "*"), "act_request", group.subs)
        self.serving.group = group
        for r, run in enumerate(runs):
            if run in retired:
                group.retired[r] = ckpt.load_retired(self.data_dir / "learner" / run)
        return [
            self._open_run(run, config, assign, MemberLearner(learner, r), evaluations[r], grouped)
            for r, (run, config) in enumerate(zip(runs, configs))
            if run not in retired
        ]

    def _open_run(
        self,
        run: str,
        config: TrainConfig,
        assign: Assignment,
        learner: MemberLearner,
        evaluations: EvaluationsInFlight,
        grouped: bool,
    ) -> LearnerRun:
        torch.set_num_threads(config.threads)
        for kind in ("transitions", "ack", "status"):
            self.listen(getattr(keys, f"k_{kind}")(run, "*"), kind, run)
        on_row = lambda key, payload: self.on_eval_row(run, evaluations, key, payload)  # noqa: E731
        self.subscribe(keys.k_metrics(run, "eval"), on_row, run)
        spec = task_spec_for(config)
        folder = self.data_dir / "learner" / run
        folder.mkdir(parents=True, exist_ok=True)
        pubs = {  # (undeclared with the run's subscriptions when it is freed)
            "weights": self.endpoint.publisher(keys.k_weights(run, "latest"), run),
            "eval": self.endpoint.publisher(keys.k_weights(run, "eval"), run),
            "ack": self.endpoint.publisher(keys.k_ack(run, self.id), run),
        }
        bonus_key = keys.k_bonus(run)
        bonus = BonusClient(
            bus_query(self.bus, bonus_key), lambda why: self.reject(bonus_key, why),
            run, config.explore, config.beta, spec.n_agents, assign.counter,
            attempt=self.served.attempts.get(run),
        )  # fmt: skip
        st = self.runs[run] = new_run(
            run, config, spec, list(assign.actors), learner=learner, bonus=bonus,
            evaluations=evaluations, pubs=pubs, counter=assign.counter, folder=folder,
            incarnation=new_incarnation(self.id), grouped=grouped,
            attempt=self.served.attempts.get(run),
        )  # fmt: skip
        return st

    def publish_provenance(self, st: LearnerRun) -> None:
        """What this start of the run runs on (shared/persist/provenance.py), once: the API
        keeps it as the run's `live.provenance`, and `macb up --out` writes it beside the
        rows."""
        start = provenance.entry(st.config.precision, st.learner.stats(), "learner")
        if self.serving.group is not None and self.serving.group.grouped:
            start["group"] = {"runs": len(self.serving.group.runs)}
        self.publish_metrics(st.run, start, source="provenance")

    def on_stop(self, run: str, reason: str) -> None:
        """A group steps together: all of it stops. Each run's last cut is written and
        its log retired."""
        for other in self.serving.group_of(run):
            st = self.runs.get(other)
            if st is not None:
                self.serving.checkpoint(st)
                ckpt.retire(st)
            self.forget(other)
            if other != run and self.serves(other):
                self.publish_status(other, "stopped", reason=f"{reason} (run {run} of its group)")
                self.free(other)

    def forget(self, run: str) -> None:
        """A run's state let go; with the group's last run, the group's subscriptions."""
        g = self.serving.group
        self.serving.drop(run)
        if g is not None and self.serving.group is None:
            self.endpoint.drop_run(g.subs)

    def on_shutdown(self) -> None:
        for st in self.runs.values():
            self.serving.checkpoint(st)

    # ------------------------------------------------------------ inbound
    def handle(self, tag: str, key: str, payload: bytes) -> None:
        t0 = time.perf_counter()
        if tag == "reject":  # found malformed on another thread (on_eval_row)
            self.reject(key, payload.decode(errors="replace"))
            return
        if tag == "act_request":
            self.on_act_request(key, payload)
            return
        msg = self.decode_for_run(key, payload, MESSAGES[tag])  # (tags are the types)
        st = self.runs.get(msg.run) if msg is not None else None
        if msg is None or st is None:
            return  # (a group's run before the group is complete has no state yet)
        try:
            self._handle(st, key, msg)
        finally:
            st.time.add("inbound", time.perf_counter() - t0)

    def _handle(self, st: LearnerRun, key: str, msg: Message) -> None:
        if isinstance(msg, Transitions):
            if not st.intake.received.knows(msg.actor):
                self.reject(key, f"unknown actor: {msg.actor}")
                return
            # A duplicate (a resend) or a gap is not taken; either way the ack tells the
            # actor again where we are, and it resends from there.
            intake.take(st, msg)
            self.out.ack(st)
        elif isinstance(msg, Ack):
            if msg.service == st.counter:
                intake.counter_acked(st, msg.acked)
        elif isinstance(msg, Status) and msg.service in st.actors:
            if msg.state == "completed":
                st.final[msg.service] = msg.final_seq or 0
            elif msg.state == "failed":
                self.fail(st, f"actor {msg.service} failed: {msg.fields()}")

    def on_act_request(self, key: str, payload: bytes) -> None:
        """A step's act request, on the lead run's keys: taken while any run of its group
        goes on (the lead's rule may have ended it first: the others still step)."""
        try:
            msg = decode(payload, ActRequest)
        except WireError as err:
            self.reject(key, str(err))
            return
        g = self.serving.group
        members = [self.runs[r] for r in g.runs if r in self.runs] if g is not None else []
        ours = g is not None and bool(members) and msg.run == g.runs[0] == keys.run_of(key)
        if not ours:
            why = self.served.refusal(keys.run_of(key), msg.run)
            if why is not None:  # ("": late traffic of a run let go, dropped silently)
                if why:
                    self.reject(key, why)
                return
        if not members:
            return  # (a group's run before the group is complete has no state yet)
        t0 = time.perf_counter()
        if why := self.serving.act_request(members[0], key, msg):
            self.reject(key, why)
        members[0].time.add("inbound", time.perf_counter() - t0)

    def on_eval_row(
        self, run: str, evaluations: EvaluationsInFlight, key: str, payload: bytes
    ) -> None:
        """The evaluator's row for a point (on Zenoh's thread; `EvaluationsInFlight`
        locks what it shares with the learner's): that evaluation is over. A malformed
        row (one `early_stop` cannot read too: that raised here, uncounted) is counted
        and logged on the service's thread (via the inbox), which owns the reject counts
        that stats() reads. A row of another attempt of the run (an ended attempt's
        evaluator, late) reports none of this attempt's points."""
        try:
            point, row, attempt = reported_row(payload)
            if self.of_attempt(run, attempt):
                evaluations.reported(point, row)  # (WireError: a row early_stop cannot read)
        except WireError as err:
            self.inbox.put(("reject", key, str(err).encode()))
        except Exception as err:  # (not Zenoh's to swallow: counted on our thread too)
            reason = f"handler raised {type(err).__name__}: {err}"
            self.log.error("an evaluation row on %.200s raised", key, exc_info=err)
            self.inbox.put(("reject", key, reason.encode()))

    def tick(self) -> bool:
        try:
            busy = self.serving.tick()
        except Diverged as err:
            if (st := self.runs.get(err.run)) is not None:
                self.fail(st, str(err))
            return False
        for st in self.serving.finished():
            self.finish(st)
        return busy

    # ------------------------------------------------------------ peers, ends
    def on_peer_found(self, role: str, peer: str) -> None:
        self.serving.peer_found(role, peer, self.assign.evaluator if self.assign else None)

    def on_peer_lost(self, role: str, peer: str) -> None:
        evaluator = self.assign.evaluator if self.assign else None
        for st, reason in self.serving.peer_lost(role, peer, evaluator, self.grace_s):
            self.fail(st, reason)

    def finish(self, st: LearnerRun) -> None:
        """Every share in replay and learnt, every point out: the run completes (or its
        `early_stop` rule held at a point: it completes there, saying why; its actor
        and counter follow, and a group's other runs go on without it: `retire`)."""
        self.serving.checkpoint(st)
        stats = self.out.stats(st).to_wire()
        goes_on = self.serving.goes_on_without(st)  # its group's other runs go on
        if goes_on:
            # Noted retired (retired.pt, the runs file) before its log goes and its end
            # is said: a restart after "completed" serves the group with it retired (in
            # the other order it rejoined the run as running, with neither log nor cut).
            self.serving.retire(st)
            self.retire(st.run)
        ckpt.retire(st)
        self.publish_metrics(st.run, stats, source="learner")
        why, at = (
            (None, {}) if st.stopped is None else (st.stopped[1], {"stopped_at": st.stopped[0]})
        )
        self.publish_status(st.run, "completed", reason=why, resumed=self.resume, **at, **stats)
        self.log.info(
            "run %s completed%s: %s", st.run, f" ({why})" if why else "", json.dumps(stats)
        )
        if not goes_on:
            self.forget(st.run)
            self.free(st.run)

    def fail(self, st: LearnerRun, reason: str) -> None:
        """A run fails, with its group (its runs step and update together)."""
        if st.run in self.runs:  # (not failed already, with its group)
            self.fail_runs(reason, self.serving.group_of(st.run))

    def fail_runs(self, reason: str, runs: list[str]) -> None:
        for run in runs:
            self.forget(run)
            if self.serves(run):
                self.log.error("run %s failed: %s", run, reason)
                self.publish_status(run, "failed", reason=reason)
                self.free(run)


def make_service(service_id: str, connect: list[str], data_dir: Path) -> LearnerService:
    return LearnerService(service_id, connect, data_dir)
