"""Central inference for `interleave: lockstep` (as SEED RL does it): the actor asks for
each step's action, and the learner answers with `act` of its current weights only once
every earlier step has been counted, taken into replay and learnt (its update done,
the weights of an episode's end out). That is the thesis's step-by-step loop, so a
run's updates, counts and weights are those of `macb train` with the same config.

`Asks` (the open request and the last answer of the runs served: a run alone, or a
group's runs, whose one actor asks for every run's action at once) is the lockstep
state, and this module its one writer: `take_request` records a request (or returns
the answer to send again when a request repeats, its answer lost), `answer` returns
the answer once it is ready, noted as given. The service publishes it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from shared.net.messages import Action, ActRequest
from shared.net.wire import WireError, encode

if TYPE_CHECKING:
    from services.learner.state import LearnerRun, RunGroup


@dataclass
class Asks:
    """The runs' one lockstep actor: its open request (every run's observation, (R,
    obs)) and the last answer, for a repeated request. A group's requests and answers
    carry one row per run; a run alone's its own (obs,) and (act,)."""

    actor: str
    action_pub: Callable[[bytes], None]  # on the lead run's keys (run 0)
    wanted: tuple[int, np.ndarray] | None = None
    answered: tuple[int, bytes] | None = None


def learnt_up_to(st: LearnerRun) -> bool:
    """Every update the run owes is done and every episode end's weights are out."""
    return st.learner.updates >= st.owed_total and not st.intake.boundaries


def take_request(g: RunGroup, obs_dim: int, msg: ActRequest) -> bytes | None:
    """The runs' request (a group's: one observation per run), kept until it can be
    answered; the answer given before if this request was answered already (the
    answer was lost). WireError for an observation the runs cannot act on."""
    asks = g.asks
    assert asks is not None
    want = (len(g.runs), obs_dim) if g.grouped else (obs_dim,)
    if msg.obs.shape != want or not np.isfinite(msg.obs).all():
        raise WireError(f"act_request: obs {msg.obs.shape}, the runs have {want}")
    if asks.answered is not None and asks.answered[0] == msg.seq:
        return asks.answered[1]
    obs = np.array(msg.obs, np.float32)
    asks.wanted = (msg.seq, obs if g.grouped else obs[None])
    return None


def ready(g: RunGroup, runs: dict[str, LearnerRun], seq: int) -> bool:
    """Every run has its steps before `seq` in replay and learnt. A run already past
    `seq` (a group's actor restarted between publishing one run's step and another's)
    does not hold the answer: that step comes again as a duplicate."""
    assert g.asks is not None
    actor = g.asks.actor
    for r, run in enumerate(g.runs):
        if r in g.retired:
            continue  # (ended by its rule: its world's steps are not published)
        st = runs.get(run)
        if st is None:
            return False
        taken = st.intake.received.expected(actor)
        if taken > seq:
            continue
        if taken < seq or not st.intake.in_replay(actor, seq) or not learnt_up_to(st):
            return False
        if st.config.early_stop is not None and (
            st.evaluations.unreported or st.evaluations.rows_in or st.stopped
        ):
            return False  # the point's row decides whether the run goes on (macb train's)
    return True


def answer(g: RunGroup, runs: dict[str, LearnerRun]) -> bytes | None:
    """The answer to the open request once it is ready: one `act` of the current
    weights for every run (the thesis's `act` after the last step's update)."""
    asks = g.asks
    if asks is None or asks.wanted is None or not ready(g, runs, asks.wanted[0]):
        return None
    seq, obs = asks.wanted
    act = g.learner.act(obs[:, None])[:, 0].astype(np.float32)
    ended = [g.runs[r] for r in sorted(g.retired)]  # (the actor retires them first)
    payload = encode(Action(g.runs[0], seq=seq, act=act if g.grouped else act[0], ended=ended))
    asks.wanted, asks.answered = None, (seq, payload)
    return payload
