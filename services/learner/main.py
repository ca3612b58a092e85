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
trip per tick instead of per update (docs/performance.md, "Learner service").

Weights go out at every episode boundary (once its updates are done), marked
`eval_point` every `eval_every` episodes. While the evaluator evaluates weights this
learner sent (`EvaluationsInFlight`), updates are marked contended so the thread tuner
can pick what is fastest beside it. An evaluation point the evaluator has not reported
is sent again (a restarted evaluator, a restarted router), and the store keeps one row
per point.

With `interleave: lockstep` the thesis's loop runs over the bus (central inference, as
SEED RL does it): the one actor sends each step's observation (`act_request`) and one
transition per step; the learner answers a request with `learner.act` of its current
weights only when every earlier step has been counted, taken into replay and learnt
(its update done, priced with counts that include it). The run's updates, counts,
weights and evaluation points are then those of `macb train` with the same config.

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

import collections
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from services.common import ServiceBase
from services.learner import checkpoint as ckpt
from services.learner import intake
from services.learner.bonus import BonusClient
from services.learner.evaluations import EvaluationsInFlight
from services.learner.state import (
    LearnerRun,
    LockstepGroup,
    MemberLearner,
    run_stats,
    update_group,
)
from shared.config import TrainConfig, actors_error
from shared.core.learners.group import GroupMADDPG
from shared.core.networks import weights_as_arrays
from shared.core.replay import ReplayBuffer, update_arrays
from shared.envs.tasks import task_spec_for
from shared.groups import group_error
from shared.net import bus as keys
from shared.net.messages import (
    MESSAGES,
    Ack,
    Action,
    ActRequest,
    Message,
    Metrics,
    Status,
    Transitions,
    Weights,
)
from shared.net.protocol import AckTracker, ReceiveCursor, episode_share
from shared.net.wire import WireError, decode, encode
from shared.persist import provenance
from shared.persist.wal import WriteAheadLog
from shared.run.factories import agent_dims, build_learner, learner_spec, minibatches_per_update
from shared.run.rollout import derive_seed

WINDOW_EPISODES = 2  # credits per actor, in episodes
MAX_BACKLOG_EPISODES = 2  # updates owed (per actor) before the window closes
UPDATES_PER_TICK = 20  # bound on work between inbox checks; one bonus query each
# Until the first transition comes, the initial weights go out again this often.
FIRST_WEIGHTS_RESEND_S = 1.0
# The columns of a logged batch, each stored as (n, bytes per row) uint8.


class LearnerService(ServiceBase):
    role = "learner"

    def __init__(self, service_id: str, connect: list[str] | None, data_dir: Path) -> None:
        super().__init__(service_id, connect, data_dir)
        self.runs: dict[str, LearnerRun] = {}  # the run served, or a group's runs
        self.group: LockstepGroup | None = None
        self._members: dict[str, TrainConfig] = {}  # a group's runs whose start came

    @property
    def st(self) -> LearnerRun | None:
        """The run served alone (None when free or serving a group)."""
        return None if self.group is not None else next(iter(self.runs.values()), None)

    # ------------------------------------------------------------ run lifecycle
    def on_start(self, run: str, config: TrainConfig, assign: dict[str, Any]) -> None:
        if assign.get("group"):
            self._members[run] = config
            if set(self._members) == set(assign["group"]):
                self.open_group(assign)
            return
        st = self._fresh(run, config, assign)
        self.publish_weights(st, eval_point=-1)  # version 0: every actor starts from these
        self.publish_status(run, "running", actors=st.actors)
        self.publish_provenance(st)

    def _group(
        self, runs: list[str], configs: list[TrainConfig], assign: dict[str, Any]
    ) -> list[LearnerRun]:
        """A group's learner, request keys and each run's state (open_group, resume_group)."""
        if why := group_error(configs, len(assign["actors"])):
            raise ValueError(why)
        spec = task_spec_for(configs[0])
        torch.set_num_threads(configs[0].threads)
        learner = GroupMADDPG(
            agent_dims(spec),
            [learner_spec(c) for c in configs],
            precision=configs[0].precision,
            device=configs[0].device,
        )
        actor, lead = assign["actors"][0], runs[0]
        self.group = LockstepGroup(
            runs, learner, actor, self.bus.publisher(keys.k_action(lead, actor))
        )
        self.listen(keys.k_act(lead, "*"), "act_request", lead)
        return [
            self._open_run(run, config, assign, MemberLearner(learner, r))
            for r, (run, config) in enumerate(zip(runs, configs))
        ]

    def _fresh(self, run: str, config: TrainConfig, assign: dict[str, Any]) -> LearnerRun:
        ckpt.wipe(self.data_dir / "learner" / run)
        st = self._open_run(run, config, assign)
        self._logged(st)
        return st

    def open_group(self, assign: dict[str, Any]) -> None:
        """Every run of a group has its start: one GroupMADDPG for them all (run r of
        `assign["group"]` is member r), each run's own intake, replay, sampler, bonus
        queries, boundaries, evaluation points and cuts."""
        runs = list(assign["group"])
        try:
            configs = [self._members.pop(run) for run in runs]
            for run in runs:
                ckpt.wipe(self.data_dir / "learner" / run)
            for st in self._group(runs, configs, assign):
                self._logged(st)
        except Exception as err:
            self.log.exception("group %s failed to start", runs)
            self.fail_group(f"{type(err).__name__}: {err}", runs)
            return
        for run in runs:
            st = self.runs[run]
            self.publish_status(run, "running", actors=st.actors, group=runs)
            self.publish_provenance(st)
        self.log.info("group of %d runs started: %s", len(runs), runs)

    def on_resume(self, run: str, config: TrainConfig, assign: dict[str, Any]) -> None:
        """Restarted mid-run: the newest good cut, then the log beyond it (module doc)."""
        if assign.get("group"):
            self._members[run] = config
            if set(self._members) == set(assign["group"]):
                self.resume_group(assign)
            return
        t0 = time.perf_counter()
        st = self._open_run(run, config, assign)
        records, _ = self._logged(st)
        cut = None
        for _, state in ckpt.good(st, self.log.warning):  # the newest good one
            st.learner.load_state_dict(state["learner"])
            cut = ckpt.apply(st, state)
            break
        self._replay(st, records, cut)
        self.resumed = self._resumed(st, cut, t0)
        self.publish_weights(st, eval_point=-1)
        self.publish_status(run, "running", actors=st.actors, resumed=self.resumed)
        self.publish_provenance(st)
        self.send_ack(st)  # the actors go on from what the log holds

    def _replay(self, st: LearnerRun, records: list, cut: int | None) -> None:
        for batch in intake.replay(st, records, cut):
            self.log.warning("run %s: logged batch %s out of order: skipped", st.run, batch)

    def _resumed(self, st: LearnerRun, cut: int | None, t0: float) -> dict[str, Any]:
        held = sum(len(h) for h in st.held.values())
        self.log.info(
            "run %s resumed from the cut at episode %s (%d updates, %d replay rows, "
            "%d logged batches beyond it) in %.2f s",
            st.run,
            cut,
            st.learner.updates,
            len(st.buffer),
            held,
            time.perf_counter() - t0,
        )
        return {
            "run": st.run,
            "from_episode": cut,
            "updates": st.learner.updates,
            "replay_rows": len(st.buffer),
            "held_batches": held,
            "seconds": round(time.perf_counter() - t0, 3),
        }

    def resume_group(self, assign: dict[str, Any]) -> None:
        """Restarted mid-group: every run from its cut at the newest update all of them
        have a cut of (a group's cuts are written together; a kill between two runs'
        files leaves the one before for some), then each run's log beyond it."""
        t0 = time.perf_counter()
        runs = list(assign["group"])
        try:
            sts = self._group(runs, [self._members.pop(run) for run in runs], assign)
            records = [self._logged(st)[0] for st in sts]
            options = [
                {
                    int(state["counters"]["updates"]): state
                    for _, state in ckpt.good(st, self.log.warning)
                }
                for st in sts
            ]
            common = set.intersection(*(set(o) for o in options))
            cuts: list[int | None] = [None] * len(sts)
            if common:
                states = [o[max(common)] for o in options]
                assert self.group is not None
                self.group.learner.load_run_state_dicts([s["learner"] for s in states])
                cuts = [ckpt.apply(st, state) for st, state in zip(sts, states)]
            elif any(options):
                self.log.warning("group %s: no update all runs have a cut of: the logs", runs)
            for st, recs, cut in zip(sts, records, cuts):
                self._replay(st, recs, cut)
        except Exception as err:
            self.log.exception("group %s failed to resume", runs)
            self.fail_group(f"{type(err).__name__}: {err}", runs)
            return
        resumed = [self._resumed(st, cut, t0) for st, cut in zip(sts, cuts)]
        self.resumed = {**resumed[0], "group": runs}
        for st, info in zip(sts, resumed):
            self.publish_status(st.run, "running", actors=st.actors, group=runs, resumed=info)
            self.publish_provenance(st)
            self.send_ack(st)

    def publish_provenance(self, st: LearnerRun) -> None:
        """What this start of the run runs on (shared/persist/provenance.py), once: the API keeps
        it as the run's `live.provenance`, and `macb up --out` writes it beside the rows."""
        start = provenance.entry(st.config.precision, st.learner.stats(), "learner")
        if self.group is not None:
            start["group"] = {"runs": len(self.group.runs)}
        self.publish_metrics(st.run, start, source="provenance")

    def _open_run(
        self,
        run: str,
        config: TrainConfig,
        assign: dict[str, Any],
        member: MemberLearner | None = None,
    ) -> LearnerRun:
        if config.bonus_at == "collection":  # the run fails, saying so (not a silent change)
            raise ValueError(
                "bonus_at collection: the cluster prices bonuses when it samples; run this "
                "config with macb train or as a run group (macb run/reproduce --local)"
            )
        torch.set_num_threads(config.threads)
        self.listen(keys.k_transitions(run, "*"), "transitions", run)
        self.listen(keys.k_ack(run, "*"), "ack", run)
        self.listen(keys.k_status(run, "*"), "status", run)
        evaluations = EvaluationsInFlight()
        self.subscribe(
            keys.k_metrics(run, "eval"),
            lambda key, payload: self.on_eval_row(evaluations, key, payload),
            run,
        )
        spec = task_spec_for(config)
        actors = list(assign["actors"])
        if why := actors_error(config, len(actors)):
            raise ValueError(why)  # the run fails, saying so
        lockstep = config.interleave == "lockstep"
        folder = self.data_dir / "learner" / run
        folder.mkdir(parents=True, exist_ok=True)
        st = self.runs[run] = LearnerRun(
            run=run,
            config=config,
            spec=spec,
            learner=member or build_learner(config, spec, contended=evaluations.busy),
            buffer=ReplayBuffer(
                min(config.buffer_size, config.episodes * config.episode_len),
                spec.joint_obs_dim,
                spec.joint_act_dim,
            ),
            rng=np.random.default_rng(derive_seed(config.seed, "sampler")),
            actors=actors,
            counter=assign.get("counter"),
            bonus=BonusClient(self, run, config.explore, config.beta, spec.n_agents),
            evaluations=evaluations,
            weights_pub=self.bus.publisher(keys.k_weights(run, "latest")),
            eval_pub=self.bus.publisher(keys.k_weights(run, "eval")),
            ack_pub=self.bus.publisher(keys.k_ack(run, self.id)),
            received=ReceiveCursor(actors=actors, partial=False),
            counted=AckTracker(actors),
            held={a: collections.deque() for a in actors},
            draws=minibatches_per_update(config),
            folder=folder,
            shares={
                a: episode_share(config.episodes, len(actors), r) * config.episode_len
                for r, a in enumerate(actors)
            },
            incarnation=f"{self.id}:{os.getpid()}:{time.time_ns()}",
            lockstep=lockstep,
            member=-1 if member is None else member.r,
        )
        if lockstep and member is None:  # (a group's requests come on its first run's keys)
            self.listen(keys.k_act(run, "*"), "act_request", run)
            st.action_pubs = {a: self.bus.publisher(keys.k_action(run, a)) for a in actors}
        return st

    def _logged(self, st: LearnerRun) -> tuple[list, WriteAheadLog]:
        """The run's log: what an earlier process of this learner took, and the log
        opened for appending (a torn last record is cut off: it was never acked)."""
        assert st.folder is not None
        log, records = WriteAheadLog.open(st.folder / "transitions.wal")
        st.log = log
        return records, log

    def on_stop(self, run: str, reason: str) -> None:
        self._members.pop(run, None)
        g = self.group
        if g is not None and run in g.runs:  # a group steps together: all of it stops
            for other in g.runs:
                if other != run and self.serves(other):
                    self._close(other)
                    self.publish_status(
                        other, "stopped", reason=f"{reason} (run {run} of its group)"
                    )
                    self.free(other)
        self._close(run)

    def _close(self, run: str) -> None:
        """A run ends here: its last cut, its log retired, its state forgotten."""
        st = self.runs.get(run)
        if st is not None:
            self.checkpoint(st)
            self.retire_log(st)
            self.drop(st)

    def drop(self, st: LearnerRun) -> None:
        """Forget a run's state (the group too, with its last run)."""
        self.runs.pop(st.run, None)
        if self.group is not None and not any(r in self.runs for r in self.group.runs):
            self.group = None

    def retire_log(self, st: LearnerRun) -> None:
        ckpt.retire(st)

    def on_shutdown(self) -> None:
        for st in self.runs.values():
            self.checkpoint(st)

    # ------------------------------------------------------------ inbound
    def handle(self, tag: str, key: str, payload: bytes) -> None:
        t0 = time.perf_counter()
        if tag == "reject":  # found malformed on another thread (on_eval_row)
            self.reject(key, payload.decode(errors="replace"))
            return
        msg = self.decode_for_run(key, payload, MESSAGES[tag])  # (tags are the types)
        st = self.runs.get(msg.run) if msg is not None else None
        if msg is None or st is None:
            return  # (a group's run before the group is complete has no state yet)
        try:
            self._handle(st, tag, key, msg)
        finally:
            st.time["inbound"] += time.perf_counter() - t0

    def _handle(self, st: LearnerRun, tag: str, key: str, msg: Message) -> None:
        if isinstance(msg, Transitions):
            self.on_transitions(st, key, msg)
        elif isinstance(msg, ActRequest):
            if self.group is not None:
                self.on_group_request(key, msg)
            else:
                self.on_act_request(st, key, msg)
        elif isinstance(msg, Ack):
            if msg.service == st.counter:
                for actor, seq in msg.acked.items():
                    st.counted.ack(actor, seq)
                intake.release_counted(st)
        elif isinstance(msg, Status) and msg.service in st.actors:
            if msg.state == "completed":
                st.final[msg.service] = int(msg.detail.get("final_seq", 0))
            elif msg.state == "failed":
                self.fail(st, f"actor {msg.service} failed: {msg.detail}")

    def on_eval_row(self, evaluations: EvaluationsInFlight, key: str, payload: bytes) -> None:
        """The evaluator's metric row for a point (on Zenoh's thread): that evaluation
        is over. Only the point is read; the API is the rows' consumer of record. A
        malformed row is counted and logged on the service's thread (via the inbox),
        which owns the reject counts that stats() reads."""
        try:
            msg = decode(payload, Metrics)
            point = msg.data["episode"]
            if not isinstance(point, int) or isinstance(point, bool):
                raise WireError(f"metrics: eval row episode is not an int: {point!r}")
        except (WireError, KeyError) as err:
            self.inbox.put(("reject", key, str(err).encode()))
            return
        evaluations.reported(point)

    def on_transitions(self, st: LearnerRun, key: str, msg: Transitions) -> None:
        if not st.received.knows(msg.actor):
            self.reject(key, f"unknown actor: {msg.actor}")
            return
        # A duplicate (a resend) or a gap is not taken; either way the ack tells the
        # actor again where we are, and it resends from there.
        intake.take(st, msg)
        self.send_ack(st)

    def tick(self) -> bool:
        if self.group is not None:
            return self.group_tick(self.group)
        st = self.st
        return False if st is None else self.run_tick(st)

    def run_tick(self, st: LearnerRun) -> bool:
        cfg, learner = st.config, st.learner
        owed = st.owed_total - learner.updates
        todo = min(owed, UPDATES_PER_TICK)
        if st.boundaries:
            todo = min(todo, max(0, st.boundaries[0].updates - learner.updates))
        spent = st.time
        t0 = time.perf_counter()
        draws = st.draws  # minibatches per update: 1, or one per agent
        if st.unpriced:  # drawn before the counter fell silent: priced now, not redrawn
            batches, st.unpriced = st.unpriced, []
        else:
            batches = [st.buffer.sample(cfg.batch_size, st.rng) for _ in range(todo * draws)]
        spent["sample"] += time.perf_counter() - t0
        st.bonus.fresh = False
        bonuses = st.bonus.bonus_for(batches) if batches else []
        if bonuses is None:
            # The counter is silent (paused, restarting): the same minibatches wait for
            # its answer, so the sampler's stream stays the one per-update draws give.
            st.unpriced, batches, bonuses = batches, [], []
        t0 = time.perf_counter()
        evaluating = st.evaluations.busy
        counts = st.bonus.counts if len(st.bonus.counts) == len(bonuses) else None
        for u in range(len(batches) // draws):
            mine = slice(u * draws, (u + 1) * draws)
            # Counted here for every kind of learner; a tuned one polls the same signal
            # for its tuners and its own count (in its stats(), which take precedence).
            contended = evaluating()
            st.contended_updates += contended
            learner.update(*update_arrays(batches[mine], bonuses[mine]))
            for j in range(mine.start, mine.stop):
                st.bonus_means.append(float(bonuses[j].mean()))
                st.diagnostics.record(bonuses[j], counts[j] if counts is not None else [])
            owed -= 1
        t1 = time.perf_counter()
        spent["update"] += t1 - t0
        self.pass_boundaries(st)
        spent["publish"] += time.perf_counter() - t1
        self.housekeep(st, owed)
        if ckpt.due(st) and not st.unpriced:
            self.checkpoint(st)  # (not with draws in hand: a cut holds the sampler after them)
        if st.lockstep and owed == 0:
            self.answer_act_requests(st)
        self.maybe_finish(st)
        return owed > 0 and st.run in self.runs

    def housekeep(self, st: LearnerRun, owed: int) -> None:
        """Between updates: the window and acks, first weights, stats, lost points."""
        now = time.monotonic()
        window_open = owed < MAX_BACKLOG_EPISODES * st.config.episode_len * len(st.actors)
        if window_open != st.window_open or now - st.last_ack > 0.5:
            st.window_open = window_open
            self.send_ack(st)
        if st.ingested == 0 and now - st.last_weights > FIRST_WEIGHTS_RESEND_S:
            # No transition yet: the first weights, which actors wait for, may have gone
            # out before the bus had a route to them.
            self.publish_weights(st, eval_point=-1)
        if now - st.last_stats > 1.0:
            st.last_stats = now
            self.publish_metrics(st.run, self.stats(st), source="learner")
        self.resend_unreported(st, now)

    # ------------------------------------------------------------ a lockstep group
    def group_tick(self, g: LockstepGroup) -> bool:
        """The group trainer's step (cli/group_trainer.py) over the bus: once every
        run has taken (and counted) this step, each samples and prices its own
        minibatches and one GroupMADDPG update updates them all; then the group's next
        request is answered with one `act` for every run."""
        members = [self.runs[r] for r in g.runs if r in self.runs]
        if (
            len(members) == len(g.runs)
            and all(st.owed_total > g.learner.updates for st in members)
            and not update_group(g, members)
        ):
            members = []  # the counter is silent: nothing more this tick
        for st in members:
            t1 = time.perf_counter()
            self.pass_boundaries(st)
            st.time["publish"] += time.perf_counter() - t1
            self.housekeep(st, st.owed_total - g.learner.updates)
        if members and ckpt.due(members[0]) and not g.unpriced:
            for st in members:  # together: a group resumes from one update
                self.checkpoint(st)
        self.answer_group(g)
        for st in members:
            self.maybe_finish(st)
        return False

    def on_group_request(self, key: str, msg: ActRequest) -> None:
        g = self.group
        assert g is not None
        if msg.actor != g.actor or keys.run_of(key) != g.runs[0]:
            self.reject(key, f"act_request from {msg.actor}: not this group's actor")
            return
        obs = msg.obs
        dim = self.runs[g.runs[0]].spec.joint_obs_dim
        if obs.shape != (len(g.runs), dim) or not np.isfinite(obs).all():
            raise WireError(f"act_request: obs {obs.shape}, the group has ({len(g.runs)}, {dim})")
        if g.answered is not None and g.answered[0] == msg.seq:
            g.action_pub(g.answered[1])  # the answer was lost: the same actions again
            return
        g.wanted = (msg.seq, np.array(obs, np.float32))

    def answer_group(self, g: LockstepGroup) -> None:
        """Act for the group's request once every run has its earlier steps counted,
        in replay and learnt: one `act` of the group's current weights for every run."""
        if g.wanted is None:
            return
        seq, obs = g.wanted
        for run in g.runs:
            st = self.runs.get(run)
            if st is None:
                return
            taken = st.received.expected(g.actor)
            if taken > seq:
                # ahead by this step (an actor restarted between publishing one run's
                # step and another's): it comes again as a duplicate after this answer
                continue
            if taken < seq or st.ingested_pos.get(g.actor, 0) != seq or st.held[g.actor]:
                return  # a step before it is not in replay yet (or not counted)
            if g.learner.updates < st.owed_total or st.boundaries:
                return  # its updates (and the weights of an episode's end) come first
        act = g.learner.act(obs[:, None])[:, 0].astype(np.float32)
        payload = encode(Action(g.runs[0], seq=seq, act=act))
        g.wanted, g.answered = None, (seq, payload)
        g.action_pub(payload)

    def fail_group(self, reason: str, runs: list[str]) -> None:
        """Every run of a group fails with one (its runs step and update together)."""
        for run in runs:
            st = self.runs.get(run)
            if st is not None:
                self.drop(st)
            if self.serves(run):
                self.log.error("run %s failed: %s", run, reason)
                self.publish_status(run, "failed", reason=reason)
                self.free(run)

    # ------------------------------------------------------------ lockstep
    def on_act_request(self, st: LearnerRun, key: str, msg: ActRequest) -> None:
        actor, obs = msg.actor, msg.obs
        if not st.lockstep or actor not in st.action_pubs:
            self.reject(key, f"act_request from {actor}: not a lockstep actor of this run")
            return
        if obs.shape != (st.spec.joint_obs_dim,) or not np.isfinite(obs).all():
            raise WireError(f"act_request: obs {obs.shape}, run has ({st.spec.joint_obs_dim},)")
        last = st.answered.get(actor)
        if last is not None and last[0] == msg.seq:
            st.action_pubs[actor](last[1])  # the answer was lost: the same action again
            return
        st.wanted[actor] = (msg.seq, np.array(obs, np.float32))

    def answer_act_requests(self, st: LearnerRun) -> None:
        """Act for each request whose earlier steps are all counted, in replay and
        learnt: the thesis's `act` with the weights after the last step's update."""
        for actor, (seq, obs) in list(st.wanted.items()):
            if seq != st.ingested_pos.get(actor, 0) or st.held[actor]:
                continue  # a step before it is not in replay yet (or not counted)
            if st.learner.updates < st.owed_total or st.boundaries:
                return  # its updates (and the weights of an episode's end) come first
            act = st.learner.act(obs[None])[0].astype(np.float32)
            payload = encode(Action(st.run, seq=seq, act=act))
            del st.wanted[actor]
            st.answered[actor] = (seq, payload)
            st.action_pubs[actor](payload)

    def pass_boundaries(self, st: LearnerRun) -> None:
        """Publish weights at each episode boundary whose updates are done."""
        while st.boundaries and st.learner.updates >= st.boundaries[0].updates:
            b = st.boundaries.popleft()
            is_eval = b.episode % st.config.eval_every == 0 or b.episode == st.config.episodes
            self.publish_weights(
                st,
                eval_point=b.episode if is_eval else -1,
                episode=b.episode,
                env_steps=b.env_steps,
                collisions=b.collisions_cum,
            )

    def publish_weights(
        self,
        st: LearnerRun,
        eval_point: int,
        episode: int = 0,
        env_steps: int = 0,
        collisions: int = 0,
    ) -> None:
        if episode:  # version 0 is the initial weights; each boundary makes a new one
            st.version += 1
        if st.member >= 0 and eval_point < 0:
            return  # a group's actor acts by request: only evaluation points need weights
        payload = encode(
            Weights(
                st.run,
                version=st.version,
                updates=st.learner.updates,
                env_steps=env_steps,
                episodes=episode,
                eval_point=eval_point,
                collisions_cum=collisions,
                actors=weights_as_arrays(st.learner.actor_weights()),
                stats={
                    **self.stats(st),
                    "counter": self.counter_stats(st) if eval_point >= 0 else {},
                    # What the bonus did on the rows sampled since the last point.
                    "bonus": st.diagnostics.take() if eval_point >= 0 else {},
                },
                incarnation=st.incarnation,
                # The points before this one that had no row when it went out: the
                # evaluator evaluates those first, so a run's rows come in episode order
                # even after an evaluator restart (the new point can beat the resends).
                unreported=sorted(p for p in st.evaluations.unreported if p < eval_point),
            )
        )
        if eval_point >= 0:
            # Noted before it goes out: the evaluator's report may come back at once.
            st.evaluations.unreported[eval_point] = (time.monotonic(), payload)
            st.evaluations.sent(eval_point)
            st.eval_pub(payload)
        else:
            st.weights_pub(payload)
            st.last_weights = time.monotonic()

    def resend_unreported(self, st: LearnerRun, now: float, at_once: bool = False) -> None:
        """Send again the evaluation points that were lost on the way
        (`EvaluationsInFlight.due`); with `at_once` all of them."""
        for point, payload in st.evaluations.due(now, at_once):
            self.log.info("run %s: evaluation point %d sent again", st.run, point)
            st.eval_pub(payload)

    def on_peer_found(self, role: str, peer: str) -> None:
        """A service of the run came back: an actor gets weights and where to go on, the
        evaluator the points it has not reported."""
        for st in list(self.runs.values()):
            if role == "actor" and peer in st.actors:
                self.publish_weights(st, eval_point=-1)
                self.send_ack(st)
            elif role == "evaluator" and peer == self.assign.get("evaluator"):
                self.resend_unreported(st, time.monotonic(), at_once=True)

    def counter_stats(self, st: LearnerRun) -> dict[str, Any]:
        """The counter's stats for this run now (table size, count-1 %, counted): from the
        reply to this tick's bonus query when there was one, else by asking the counter."""
        if not st.counting or not st.counter:
            return {}  # no tables: a point says 0 counted, as the one-process trainer
        if st.bonus.tables is not None and st.bonus.fresh:
            return dict(st.bonus.tables)
        for raw in self.bus.get(keys.k_info("counter", st.counter), timeout=1.0):
            try:
                return dict(json.loads(raw).get("runs", {}).get(st.run, {}))
            except (ValueError, AttributeError, TypeError):
                return {}
        return {}

    def send_ack(self, st: LearnerRun) -> None:
        st.last_ack = time.monotonic()
        window = WINDOW_EPISODES * st.config.episode_len if st.window_open else 0
        st.ack_pub(
            encode(Ack(st.run, service=self.id, acked=st.received.positions(), window=window))
        )

    def stats(self, st: LearnerRun) -> dict[str, Any]:
        return run_stats(st, sum(self.rejects.values()))

    def maybe_finish(self, st: LearnerRun) -> None:
        if not st.done:
            return
        run = st.run
        self.checkpoint(st)
        self.retire_log(st)
        stats = self.stats(st)
        self.publish_metrics(run, stats, source="learner")
        self.publish_status(run, "completed", **stats, resumed=self.resumed)
        self.log.info("run %s completed: %s", run, json.dumps(stats))
        self.drop(st)
        self.free(run)

    def on_peer_lost(self, role: str, peer: str) -> None:
        """A peer of the run that died and did not come back within the grace period
        fails the run: an actor's transitions, or the evaluator's rows, cannot come."""
        for st in list(self.runs.values()):
            if role == "evaluator" and peer == self.assign.get("evaluator"):
                why = f"evaluator {peer} died and did not come back within {self.grace_s:g} s"
                self.fail(st, why)
            elif role == "actor" and peer in st.actors and peer not in st.final:
                self.fail(
                    st,
                    f"actor {peer} died before it finished its episodes "
                    f"(not back within {self.grace_s:g} s)",
                )

    def fail(self, st: LearnerRun, reason: str) -> None:
        if st.run not in self.runs:
            return  # failed already (with its group)
        if self.group is not None and st.run in self.group.runs:
            self.fail_group(reason, list(self.group.runs))
            return
        run = st.run
        self.log.error("run %s failed: %s", run, reason)
        self.publish_status(run, "failed", reason=reason)
        self.drop(st)
        self.free(run)

    def checkpoint(self, st: LearnerRun) -> None:
        """A cut of the run (services/learner/checkpoint.py)."""
        if st.folder is None:
            return
        spent = ckpt.write(st)
        self.log.debug(
            "run %s: cut at episode %d (%d bytes, %.1f ms)",
            st.run,
            st.episodes,
            st.cut_bytes,
            1e3 * spent,
        )


def make_service(service_id: str, connect: list[str], data_dir: Path) -> LearnerService:
    return LearnerService(service_id, connect, data_dir)
