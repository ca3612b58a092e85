"""The learner's updates at the thesis's replay ratio: one per transition taken beyond
`learning_starts`, each on minibatches sampled from the run's replay and priced by its
`BonusClient` at sample time.

`Sampling` is a run's sampling state (the sampler's RNG, minibatches drawn and not yet
priced, what the bonuses were) and this module its one writer. `update` does a tick's
updates of the runs served, a run alone or a lockstep group's (one learner call per
update for every run: a run alone's learner is a group of one). Minibatches drawn for
a query the counter did not answer are kept and priced again, never redrawn, so the
sampler's stream is the one per-update sampling gives. No bus here beyond the bonus
client's query.
"""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.core.exploration import BonusDiagnostics, price
from shared.core.replay import update_arrays

if TYPE_CHECKING:
    from services.learner.state import LearnerRun, RunGroup

UPDATES_PER_TICK = 20  # bound on work between inbox checks; one bonus query each


@dataclass
class Sampling:
    """A run's minibatches: drawn with `rng`, priced, learnt from."""

    rng: np.random.Generator
    per_update: int = 1  # minibatches per update: 1, or one per agent (`minibatch: per-agent`)
    unpriced: list = field(default_factory=list)  # drawn, bonus query unanswered
    contended_updates: int = 0
    bonus_means: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=100)
    )
    diagnostics: BonusDiagnostics = field(default_factory=BonusDiagnostics)

    def load_rng(self, state: dict[str, Any]) -> None:
        """The sampler where a cut left it."""
        self.rng.bit_generator.state = state

    def learnt(self, bonuses: list[np.ndarray], counts: list | None) -> None:
        """What the bonuses of minibatches learnt from were (the stats and diagnostics)."""
        for j, bonus in enumerate(bonuses):
            self.bonus_means.append(float(bonus.mean()))
            self.diagnostics.record(bonus, counts[j] if counts is not None else [])


def updates_due(st: LearnerRun) -> int:
    """This tick's updates: what the replay ratio owes, at most UPDATES_PER_TICK, and
    never past the next episode boundary (its weights go out first)."""
    todo = min(st.owed_total - st.learner.updates, UPDATES_PER_TICK)
    if st.intake.boundaries:
        todo = min(todo, max(0, st.intake.boundaries[0].updates - st.learner.updates))
    return todo


def update(g: RunGroup, members: list[LearnerRun], todo: int) -> int:
    """Up to `todo` updates of the runs served (a run alone, or every run of a group
    with one learner call per update), each run's minibatches priced in one bonus query
    (a group's queries sent at once, so their round trips overlap); the number done (0
    while a counter is silent: the same minibatches wait for its answer, so the
    sampler's streams stay the ones per-update sampling gives)."""
    t0 = time.perf_counter()
    drawn = [st.sampling.unpriced for st in members]
    if not any(drawn):  # else drawn before a counter fell silent: priced now, not redrawn
        drawn = [
            [st.intake.buffer.sample(st.config.batch_size, st.sampling.rng) for _ in range(n)]
            for st in members
            for n in [todo * st.sampling.per_update]
        ]
    for st in members:
        st.sampling.unpriced = []
        st.bonus.fresh = False
    t1 = time.perf_counter()
    if not any(drawn):
        return 0
    queries = [st.bonus.ask(batches) for st, batches in zip(members, drawn)]
    priced = []
    for st, query in zip(members, queries):
        bonuses = st.bonus.answer(query)
        if bonuses is None:
            for m, batches in zip(members, drawn):
                m.sampling.unpriced = batches
            return 0
        known = st.bonus.counts
        counts = list(known) if len(known) == len(bonuses) else None
        if st.config.beta_schedule is not None:
            bonuses = scheduled(st, bonuses, counts, g.learner.updates)
        priced.append((bonuses, counts))
    t2 = time.perf_counter()
    per = members[0].sampling.per_update  # 1, or one per agent
    done = len(drawn[0]) // per
    for u in range(done):
        mine = slice(u * per, (u + 1) * per)
        fresh = {}
        for st, batches, (bonuses, _) in zip(members, drawn, priced):
            # Counted here for every kind of learner; a tuned one polls the same signal
            # for its tuners and its own count (in its stats(), which take precedence).
            st.sampling.contended_updates += st.evaluations.busy()
            fresh[st.run] = update_arrays(batches[mine], bonuses[mine])
        # (a run its early_stop rule ended: its fixed arrays, nothing drawn or priced)
        parts = [g.retired[r] if r in g.retired else fresh[run] for r, run in enumerate(g.runs)]
        g.learner.update(*[np.stack(cols) for cols in zip(*parts)])
        for st, (bonuses, counts) in zip(members, priced):
            st.sampling.learnt(bonuses[mine], counts[mine] if counts is not None else None)
    spent = time.perf_counter() - t2
    for st in members:
        st.time.add("sample", (t1 - t0) / len(members))
        st.time.add("update", spent / len(members))
    return done


def scheduled(
    st: LearnerRun, bonuses: list[np.ndarray], counts: list | None, updates: int
) -> list[np.ndarray]:
    """A tick's bonuses at the schedule's beta (`beta_schedule`): minibatch j belongs to
    update `updates + j // per + 1`, the one the replay ratio owes for transition
    `learning_starts` + that, so it is priced at that transition's beta, as `macb train`
    prices it, from the counts the counter answered with (its own bonus is at the
    config's beta)."""
    cfg, per = st.config, st.sampling.per_update
    out = []
    for j, bonus in enumerate(bonuses):
        beta = cfg.beta_at(cfg.learning_starts + updates + j // per + 1)
        if counts is not None or not cfg.counts:
            tables = [np.maximum(c, 1) for c in counts[j]] if counts is not None else []
            out.append(price(cfg.explore, tables, beta, len(bonus), st.spec.n_agents))
        else:  # (a reply without its counts: the counter's bonus rescaled)
            scale = beta / cfg.beta if cfg.beta else 0.0
            out.append((bonus * np.float32(scale)).astype(np.float32))
    return out
