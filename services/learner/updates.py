"""The learner's updates at the thesis's replay ratio: one per transition taken beyond
`learning_starts`, each on minibatches sampled from the run's replay and priced by its
`BonusClient` at sample time.

`Sampling` is a run's sampling state (the sampler's RNG, minibatches drawn and not yet
priced, what the bonuses were) and this module its one writer. `update_run` does a
tick's updates for a run served alone, `update_group` one update of every run of a
lockstep group (one `GroupMADDPG` call). Minibatches drawn for a query the counter did
not answer are kept and priced again, never redrawn, so the sampler's stream is the one
per-update sampling gives. No bus here beyond the bonus client's query.
"""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.core.exploration import BonusDiagnostics
from shared.core.replay import update_arrays

if TYPE_CHECKING:
    from services.learner.lockstep import LockstepGroup
    from services.learner.state import LearnerRun

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

    def rng_state(self) -> dict[str, Any]:
        return dict(self.rng.bit_generator.state)

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


def update_run(st: LearnerRun, todo: int) -> int:
    """Up to `todo` updates of a run served alone, their minibatches priced in one
    bonus query; the number done (0 while the counter is silent)."""
    sp, per = st.sampling, st.sampling.per_update  # 1, or one per agent
    t0 = time.perf_counter()
    if sp.unpriced:  # drawn before the counter fell silent: priced now, not redrawn
        batches, sp.unpriced = sp.unpriced, []
    else:
        batches = [st.intake.buffer.sample(st.config.batch_size, sp.rng) for _ in range(todo * per)]
    st.time.add("sample", time.perf_counter() - t0)
    st.bonus.fresh = False
    bonuses = st.bonus.bonus_for(batches) if batches else []
    if bonuses is None:
        # The counter is silent (paused, restarting): the same minibatches wait for
        # its answer, so the sampler's stream stays the one per-update sampling gives.
        sp.unpriced = batches
        return 0
    t0 = time.perf_counter()
    evaluating = st.evaluations.busy
    counts = st.bonus.counts if len(st.bonus.counts) == len(bonuses) else None
    done = len(batches) // per
    for u in range(done):
        mine = slice(u * per, (u + 1) * per)
        # Counted here for every kind of learner; a tuned one polls the same signal
        # for its tuners and its own count (in its stats(), which take precedence).
        sp.contended_updates += evaluating()
        st.learner.update(*update_arrays(batches[mine], bonuses[mine]))
        sp.learnt(bonuses[mine], counts[mine] if counts is not None else None)
    st.time.add("update", time.perf_counter() - t0)
    return done


def update_group(g: LockstepGroup, members: list[LearnerRun]) -> bool:
    """One update of every run of the group; False if a bonus query went
    unanswered (the same minibatches wait for the counter, as a run's do)."""
    t0 = time.perf_counter()
    batch = members[0].config.batch_size
    drawn = [st.sampling.unpriced for st in members]
    if not any(drawn):
        drawn = [
            [st.intake.buffer.sample(batch, st.sampling.rng) for _ in range(st.sampling.per_update)]
            for st in members
        ]
    t1 = time.perf_counter()
    for st in members:
        st.bonus.fresh = False
    queries = [st.bonus.ask(batches) for st, batches in zip(members, drawn)]
    priced = []
    for st, query in zip(members, queries):
        bonuses = st.bonus.answer(query)
        if bonuses is None:
            for m, batches in zip(members, drawn):
                m.sampling.unpriced = batches
            return False
        priced.append((bonuses, list(st.bonus.counts)))
    for st in members:
        st.sampling.unpriced = []
    t2 = time.perf_counter()
    parts = [update_arrays(b, p[0]) for b, p in zip(drawn, priced)]
    g.learner.update(*[np.stack(cols) for cols in zip(*parts)])
    spent = time.perf_counter() - t2
    for st, (bonuses, counts) in zip(members, priced):
        st.time.add("sample", (t1 - t0) / len(members))
        st.time.add("update", spent / len(members))
        st.sampling.learnt(bonuses, counts if len(counts) == len(bonuses) else None)
    return True
