"""The learner's updates at the thesis's replay ratio: one per transition taken beyond
`learning_starts`, each on minibatches sampled from the run's replay and priced by its
`BonusClient` at sample time.

`update_run` does a tick's updates for a run served alone, `update_group` one update
of every run of a lockstep group (one `GroupMADDPG` call). Minibatches drawn for a
query the counter did not answer are kept and priced again, never redrawn, so the
sampler's stream is the one per-update sampling gives. No bus here beyond the bonus
client's query.
"""

from __future__ import annotations

import time

import numpy as np

from services.learner.state import LearnerRun, LockstepGroup
from shared.core.replay import update_arrays

UPDATES_PER_TICK = 20  # bound on work between inbox checks; one bonus query each


def updates_due(st: LearnerRun) -> int:
    """This tick's updates: what the replay ratio owes, at most UPDATES_PER_TICK, and
    never past the next episode boundary (its weights go out first)."""
    todo = min(st.owed_total - st.learner.updates, UPDATES_PER_TICK)
    if st.boundaries:
        todo = min(todo, max(0, st.boundaries[0].updates - st.learner.updates))
    return todo


def update_run(st: LearnerRun, todo: int) -> int:
    """Up to `todo` updates of a run served alone, their minibatches priced in one
    bonus query; the number done (0 while the counter is silent)."""
    spent, per = st.time, st.minibatches_per_update  # 1, or one per agent
    t0 = time.perf_counter()
    if st.unpriced:  # drawn before the counter fell silent: priced now, not redrawn
        batches, st.unpriced = st.unpriced, []
    else:
        batches = [st.buffer.sample(st.config.batch_size, st.rng) for _ in range(todo * per)]
    spent["sample"] += time.perf_counter() - t0
    st.bonus.fresh = False
    bonuses = st.bonus.bonus_for(batches) if batches else []
    if bonuses is None:
        # The counter is silent (paused, restarting): the same minibatches wait for
        # its answer, so the sampler's stream stays the one per-update sampling gives.
        st.unpriced = batches
        return 0
    t0 = time.perf_counter()
    evaluating = st.evaluations.busy
    counts = st.bonus.counts if len(st.bonus.counts) == len(bonuses) else None
    done = len(batches) // per
    for u in range(done):
        mine = slice(u * per, (u + 1) * per)
        # Counted here for every kind of learner; a tuned one polls the same signal
        # for its tuners and its own count (in its stats(), which take precedence).
        contended = evaluating()
        st.contended_updates += contended
        st.learner.update(*update_arrays(batches[mine], bonuses[mine]))
        for j in range(mine.start, mine.stop):
            st.bonus_means.append(float(bonuses[j].mean()))
            st.diagnostics.record(bonuses[j], counts[j] if counts is not None else [])
    spent["update"] += time.perf_counter() - t0
    return done


def update_group(g: LockstepGroup, members: list[LearnerRun]) -> bool:
    """One update of every run of the group; False if a bonus query went
    unanswered (the same minibatches wait for the counter, as a run's do)."""
    t0 = time.perf_counter()
    batch = members[0].config.batch_size
    drawn = g.unpriced or [
        [st.buffer.sample(batch, st.rng) for _ in range(st.minibatches_per_update)]
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
            g.unpriced = drawn
            return False
        priced.append((bonuses, list(st.bonus.counts)))
    g.unpriced = []
    t2 = time.perf_counter()
    parts = [update_arrays(b, p[0]) for b, p in zip(drawn, priced)]
    g.learner.update(*[np.stack(cols) for cols in zip(*parts)])
    spent = time.perf_counter() - t2
    for st, (bonuses, counts) in zip(members, priced):
        st.time["sample"] += (t1 - t0) / len(members)
        st.time["update"] += spent / len(members)
        for j, bonus in enumerate(bonuses):
            st.bonus_means.append(float(bonus.mean()))
            st.diagnostics.record(bonus, counts[j] if len(counts) == len(bonuses) else [])
    return True
