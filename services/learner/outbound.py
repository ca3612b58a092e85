"""What the learner sends for a run, and when: acks with the actors' credit window,
weights at each episode boundary whose updates are done (every `eval_every` episodes
an evaluation point for the evaluator, kept until its row comes back and sent again
when lost), the first weights until the first transition comes, and stats.

`Outgoing` is a run's outbound state (its publishers, the weights version, the credit
window, when each thing last went out) and this module its one writer. `Outbound`
keeps no run state: it reads a `LearnerRun`, writes its `Outgoing` and sends through
the run's publishers and the callables it is given, so what goes out when is tested in
process with publishers that record.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.core.networks import weights_as_arrays
from shared.net.info import CounterInfo
from shared.net.messages import Ack, Weights
from shared.net.stats import LearnerStats
from shared.net.wire import encode

if TYPE_CHECKING:
    from services.learner.state import LearnerRun

WINDOW_EPISODES = 2  # credits per actor, in episodes
MAX_BACKLOG_EPISODES = 2  # updates owed (per actor) before the window closes
# Until the first transition comes, the initial weights go out again this often.
FIRST_WEIGHTS_RESEND_S = 1.0


@dataclass
class Outgoing:
    """What goes out for a run: through which publishers, which weights version, the
    actors' credit window, and when each last went."""

    weights_pub: Callable[[bytes], None]
    eval_pub: Callable[[bytes], None]
    ack_pub: Callable[[bytes], None]
    incarnation: str = ""  # this process's weights are newer than any before a restart
    attempt: int | None = None  # the run's attempt (Start.attempt), on every Weights
    to_actors: bool = True  # False for a group's run: its actor acts by request
    version: int = 0
    window_open: bool = True
    last_ack: float = 0.0
    last_weights: float = 0.0  # when weights last went to the actors
    last_stats: float = 0.0
    t0: float = field(default_factory=time.perf_counter)  # the stats' wall clock

    def restore_version(self, version: int) -> None:
        """A cut's version: the weights go on numbered from there."""
        self.version = version

    def version_at_least(self, version: int) -> None:
        """An actor acted with weights `version` (read back from the log after a
        restart): later weights are numbered above it, so the lags stay >= 0."""
        self.version = max(self.version, version)


class Diverged(Exception):
    """A run's learner went to NaN or infinity: the actors and the evaluator refuse such
    weights (they would act and evaluate on nothing), so the run fails, saying so,
    rather than waiting for rows that never come."""

    def __init__(self, run: str, why: str) -> None:
        super().__init__(f"run {run}: {why}")
        self.run = run


def run_stats(st: LearnerRun, rejects_total: int) -> LearnerStats:
    """The run's learner stats: progress, replay ratio and lag, where the time per update
    goes, the bonus queries, the cuts, and the learner's own."""
    updates, it, sp, cuts = st.learner.updates, st.intake, st.sampling, st.cuts
    owed_total = st.owed_total
    wall = time.perf_counter() - st.outgoing.t0
    lat = sorted(st.bonus.latencies)
    per_update = 1e3 / updates if updates else 0.0
    phases = {**st.time.spent, "bonus_wait": st.bonus.wait_s}
    spent = {k: v * per_update for k, v in phases.items()}
    spent["other"] = (wall - sum(phases.values())) * per_update
    return LearnerStats(
        updates=updates,
        ingested=it.ingested,
        episodes_ingested=it.episodes,
        replay_ratio=updates / owed_total if owed_total else 0.0,
        policy_lag=float(np.mean(it.lags)) if it.lags else 0.0,
        policy_version=st.outgoing.version,
        wall_s=wall,
        steps_per_sec=it.ingested / wall if wall > 0 else 0.0,
        updates_per_sec=updates / wall if wall > 0 else 0.0,
        backlog=owed_total - updates,
        window_open=st.outgoing.window_open,
        bonus_p50_ms=1e3 * lat[len(lat) // 2] if lat else 0.0,
        bonus_p99_ms=1e3 * lat[int(len(lat) * 0.99)] if lat else 0.0,
        bonus_wait_ms_per_update=spent["bonus_wait"],
        bonus_queries=st.bonus.queries,
        bonus_rows_per_query=st.bonus.rows / max(1, st.bonus.queries),
        bonus_failures=st.bonus.failures,
        bonus_unanswered=st.bonus.unanswered,
        bonus_refused=st.bonus.refused,
        bonus_mean=float(np.mean(sp.bonus_means)) if sp.bonus_means else 0.0,
        rejects_total=rejects_total,
        contended_updates=sp.contended_updates,
        eval_rows_seen=st.evaluations.reported_rows,
        cuts=cuts.written,
        cut_ms_mean=1e3 * cuts.seconds / cuts.written if cuts.written else 0.0,
        cut_bytes=cuts.size,
        spent=spent,
        own=st.learner.stats(),
    )


class Outbound:
    """A learner's messages for the runs it serves.

    `metrics(run, data, source)` publishes a metrics row, `rejects_total()` is the
    service's malformed-message count (in every stats row), `counter_info(counter)` asks
    a counter for its info (the replies, as JSON bytes)."""

    def __init__(
        self,
        service_id: str,
        metrics: Callable[..., None],
        rejects_total: Callable[[], int],
        counter_info: Callable[[str], list[bytes]],
        log: logging.Logger,
    ) -> None:
        self.id, self.metrics, self.rejects_total = service_id, metrics, rejects_total
        self.counter_info, self.log = counter_info, log

    def stats(self, st: LearnerRun) -> LearnerStats:
        return run_stats(st, self.rejects_total())

    def ack(self, st: LearnerRun) -> None:
        """Where the learner is with each actor, and the credit window (closed while
        the learner is behind: actors wait rather than let the replay ratio drift)."""
        out = st.outgoing
        out.last_ack = time.monotonic()
        window = WINDOW_EPISODES * st.config.episode_len if out.window_open else 0
        positions = st.intake.received.positions()
        ack = Ack(st.run, service=self.id, acked=positions, window=window, attempt=out.attempt)
        out.ack_pub(encode(ack))

    def weights(
        self,
        st: LearnerRun,
        eval_point: int,
        episode: int = 0,
        env_steps: int = 0,
        collisions: int = 0,
    ) -> None:
        """The run's weights: to the actors, or as evaluation point `eval_point` (>= 0)
        to the evaluator, noted as unreported until its row comes."""
        out = st.outgoing
        if episode:  # version 0 is the initial weights; each boundary makes a new one
            out.version += 1
        if not out.to_actors and eval_point < 0:
            return  # a group's actor acts by request: only evaluation points need weights
        payload = encode(self.weights_message(st, eval_point, episode, env_steps, collisions))
        if eval_point >= 0:
            # Noted before it goes out: the evaluator's report may come back at once.
            st.evaluations.sent(eval_point, payload)
            out.eval_pub(payload)
        else:
            out.weights_pub(payload)
            out.last_weights = time.monotonic()

    def weights_message(
        self, st: LearnerRun, eval_point: int, episode: int, env_steps: int, collisions: int
    ) -> Weights:
        point = eval_point >= 0
        actors = weights_as_arrays(st.learner.actor_weights())
        if not all(np.isfinite(a).all() for sd in actors for a in sd.values()):
            raise Diverged(st.run, f"its learner's weights are not finite at update "
                           f"{st.learner.updates} (diverged)")  # fmt: skip
        return Weights(
            st.run,
            version=st.outgoing.version,
            updates=st.learner.updates,
            env_steps=env_steps,
            episodes=episode,
            eval_point=eval_point,
            collisions_cum=collisions,
            actors=actors,
            stats=dataclasses.replace(
                self.stats(st),
                counter=self.counter_stats(st) if point else {},
                # What the bonus did on the rows sampled since the last point.
                bonus=st.sampling.diagnostics.take() if point else {},
            ).to_wire(),
            incarnation=st.outgoing.incarnation,
            attempt=st.outgoing.attempt,
            # The points before this one that had no row when it went out: the
            # evaluator evaluates those first, so a run's rows come in episode order
            # even after an evaluator restart (the new point can beat the resends).
            unreported=st.evaluations.unreported_before(eval_point),
        )

    def boundaries(self, st: LearnerRun) -> None:
        """Weights at each episode boundary whose updates are done."""
        t0 = time.perf_counter()
        while (b := st.intake.boundary_done(st.learner.updates)) is not None:
            is_eval = b.episode % st.config.eval_every == 0 or b.episode == st.config.episodes
            self.weights(
                st,
                eval_point=b.episode if is_eval else -1,
                episode=b.episode,
                env_steps=b.env_steps,
                collisions=b.collisions_cum,
            )
        st.time.add("publish", time.perf_counter() - t0)

    def resend(self, st: LearnerRun, now: float, at_once: bool = False) -> None:
        """Send again the evaluation points that were lost on the way
        (`EvaluationsInFlight.due`); with `at_once` all of them."""
        for point, payload in st.evaluations.due(now, at_once):
            self.log.info("run %s: evaluation point %d sent again", st.run, point)
            st.outgoing.eval_pub(payload)

    def housekeep(self, st: LearnerRun, owed: int) -> None:
        """Between updates: the window and acks, first weights, stats, lost points."""
        now, out = time.monotonic(), st.outgoing
        window_open = owed < MAX_BACKLOG_EPISODES * st.config.episode_len * len(st.actors)
        if window_open != out.window_open or now - out.last_ack > 0.5:
            out.window_open = window_open
            self.ack(st)
        if st.intake.ingested == 0 and now - out.last_weights > FIRST_WEIGHTS_RESEND_S:
            # No transition yet: the first weights, which actors wait for, may have gone
            # out before the bus had a route to them.
            self.weights(st, eval_point=-1)
        if now - out.last_stats > 1.0:
            out.last_stats = now
            self.metrics(st.run, self.stats(st).to_wire(), source="learner")
        self.resend(st, now)

    def counter_stats(self, st: LearnerRun) -> dict[str, Any]:
        """The counter's stats for this run now (table size, count-1 %, counted): from the
        reply to this tick's bonus query when there was one, else by asking the counter."""
        if not st.counting or not st.counter:
            return {}  # no tables: a point says 0 counted, as the one-process trainer
        if st.bonus.tables is not None and st.bonus.fresh:
            return dict(st.bonus.tables)
        for raw in self.counter_info(st.counter):
            try:
                info = CounterInfo.from_json(json.loads(raw))
            except (ValueError, AttributeError, TypeError):
                return {}
            return {} if info is None else dict(info.run_stats.get(st.run, {}))
        return {}
