"""What the learner sends for a run, and when: acks with the actors' credit window,
weights at each episode boundary whose updates are done (every `eval_every` episodes
an evaluation point for the evaluator, kept until its row comes back and sent again
when lost), the first weights until the first transition comes, and stats.

`Outbound` keeps no run state: it reads and writes a `LearnerRun` and sends through the
run's publishers and the callables it is given, so what goes out when is tested in
process with publishers that record.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable
from typing import Any

from services.learner.state import LearnerRun, run_stats
from shared.core.networks import weights_as_arrays
from shared.net.messages import Ack, Weights
from shared.net.wire import encode

WINDOW_EPISODES = 2  # credits per actor, in episodes
MAX_BACKLOG_EPISODES = 2  # updates owed (per actor) before the window closes
# Until the first transition comes, the initial weights go out again this often.
FIRST_WEIGHTS_RESEND_S = 1.0


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

    def stats(self, st: LearnerRun) -> dict[str, Any]:
        return run_stats(st, self.rejects_total())

    def ack(self, st: LearnerRun) -> None:
        """Where the learner is with each actor, and the credit window (closed while
        the learner is behind: actors wait rather than let the replay ratio drift)."""
        st.last_ack = time.monotonic()
        window = WINDOW_EPISODES * st.config.episode_len if st.window_open else 0
        st.ack_pub(
            encode(Ack(st.run, service=self.id, acked=st.received.positions(), window=window))
        )

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
        if episode:  # version 0 is the initial weights; each boundary makes a new one
            st.version += 1
        if st.member >= 0 and eval_point < 0:
            return  # a group's actor acts by request: only evaluation points need weights
        payload = encode(self.weights_message(st, eval_point, episode, env_steps, collisions))
        if eval_point >= 0:
            # Noted before it goes out: the evaluator's report may come back at once.
            st.evaluations.unreported[eval_point] = (time.monotonic(), payload)
            st.evaluations.sent(eval_point)
            st.eval_pub(payload)
        else:
            st.weights_pub(payload)
            st.last_weights = time.monotonic()

    def weights_message(
        self, st: LearnerRun, eval_point: int, episode: int, env_steps: int, collisions: int
    ) -> Weights:
        point = eval_point >= 0
        return Weights(
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
                "counter": self.counter_stats(st) if point else {},
                # What the bonus did on the rows sampled since the last point.
                "bonus": st.diagnostics.take() if point else {},
            },
            incarnation=st.incarnation,
            # The points before this one that had no row when it went out: the
            # evaluator evaluates those first, so a run's rows come in episode order
            # even after an evaluator restart (the new point can beat the resends).
            unreported=sorted(p for p in st.evaluations.unreported if p < eval_point),
        )

    def boundaries(self, st: LearnerRun) -> None:
        """Weights at each episode boundary whose updates are done."""
        t0 = time.perf_counter()
        while st.boundaries and st.learner.updates >= st.boundaries[0].updates:
            b = st.boundaries.popleft()
            is_eval = b.episode % st.config.eval_every == 0 or b.episode == st.config.episodes
            self.weights(
                st,
                eval_point=b.episode if is_eval else -1,
                episode=b.episode,
                env_steps=b.env_steps,
                collisions=b.collisions_cum,
            )
        st.time["publish"] += time.perf_counter() - t0

    def resend(self, st: LearnerRun, now: float, at_once: bool = False) -> None:
        """Send again the evaluation points that were lost on the way
        (`EvaluationsInFlight.due`); with `at_once` all of them."""
        for point, payload in st.evaluations.due(now, at_once):
            self.log.info("run %s: evaluation point %d sent again", st.run, point)
            st.eval_pub(payload)

    def housekeep(self, st: LearnerRun, owed: int) -> None:
        """Between updates: the window and acks, first weights, stats, lost points."""
        now = time.monotonic()
        window_open = owed < MAX_BACKLOG_EPISODES * st.config.episode_len * len(st.actors)
        if window_open != st.window_open or now - st.last_ack > 0.5:
            st.window_open = window_open
            self.ack(st)
        if st.ingested == 0 and now - st.last_weights > FIRST_WEIGHTS_RESEND_S:
            # No transition yet: the first weights, which actors wait for, may have gone
            # out before the bus had a route to them.
            self.weights(st, eval_point=-1)
        if now - st.last_stats > 1.0:
            st.last_stats = now
            self.metrics(st.run, self.stats(st), source="learner")
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
                return dict(json.loads(raw).get("runs", {}).get(st.run, {}))
            except (ValueError, AttributeError, TypeError):
                return {}
        return {}
