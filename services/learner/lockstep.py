"""Central inference for `interleave: lockstep` (as SEED RL does it): the actor asks for
each step's action, and the learner answers with `act` of its current weights only once
every earlier step has been counted, taken into replay and learnt (its update done,
the weights of an episode's end out). That is the thesis's step-by-step loop, so a
run's updates, counts and weights are those of `macb train` with the same config.

`Asks` (a lone run's open requests and last answers) and `LockstepGroup` (a group's)
are the lockstep state, and this module their one writer: `take_*` records a request
(or returns the answer to send again when a request repeats, its answer lost),
`answers`/`group_answer` return the answers that are ready, noted as given. The
service publishes them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from shared.core.learners.group import GroupMADDPG
from shared.net.messages import Action, ActRequest
from shared.net.wire import WireError, encode

if TYPE_CHECKING:
    from services.learner.state import LearnerRun


@dataclass
class Asks:
    """A lone lockstep run's requests: the open one of each actor, the last answers."""

    pubs: dict[str, Callable[[bytes], None]] = field(default_factory=dict)  # per actor
    wanted: dict[str, tuple[int, np.ndarray]] = field(default_factory=dict)
    answered: dict[str, tuple[int, bytes]] = field(default_factory=dict)


@dataclass
class LockstepGroup:
    """A run group served in lockstep: one learner for its runs (run r of `runs` is
    member r), one actor stepping their worlds, one act request per step for all."""

    runs: list[str]
    learner: GroupMADDPG
    actor: str
    action_pub: Callable[[bytes], None]
    wanted: tuple[int, np.ndarray] | None = None  # the open request: (seq, (R, obs))
    answered: tuple[int, bytes] | None = None  # the last answer, for a repeated request


def learnt_up_to(st: LearnerRun) -> bool:
    """Every update the run owes is done and every episode end's weights are out."""
    return st.learner.updates >= st.owed_total and not st.intake.boundaries


def take_request(st: LearnerRun, msg: ActRequest) -> bytes | None:
    """A lone run's request, kept until it can be answered; the answer given before if
    this request was answered already (the answer was lost). WireError for an
    observation the run cannot act on."""
    dim = st.spec.joint_obs_dim
    if msg.obs.shape != (dim,) or not np.isfinite(msg.obs).all():
        raise WireError(f"act_request: obs {msg.obs.shape}, run has ({dim},)")
    last = st.asks.answered.get(msg.actor)
    if last is not None and last[0] == msg.seq:
        return last[1]
    st.asks.wanted[msg.actor] = (msg.seq, np.array(msg.obs, np.float32))
    return None


def answers(st: LearnerRun) -> list[tuple[str, bytes]]:
    """(actor, action message) for each request whose earlier steps are all in replay
    and learnt: the thesis's `act` with the weights after the last step's update."""
    out, asks = [], st.asks
    for actor, (seq, obs) in list(asks.wanted.items()):
        if not st.intake.in_replay(actor, seq):
            continue  # a step before it is not in replay yet (or not counted)
        if not learnt_up_to(st):
            break  # its updates (and the weights of an episode's end) come first
        act = st.learner.act(obs[None])[0].astype(np.float32)
        payload = encode(Action(st.run, seq=seq, act=act))
        del asks.wanted[actor]
        asks.answered[actor] = (seq, payload)
        out.append((actor, payload))
    return out


def take_group_request(g: LockstepGroup, obs_dim: int, msg: ActRequest) -> bytes | None:
    """A group's request (one observation per run), as `take_request` does a run's."""
    obs = msg.obs
    if obs.shape != (len(g.runs), obs_dim) or not np.isfinite(obs).all():
        raise WireError(f"act_request: obs {obs.shape}, the group has ({len(g.runs)}, {obs_dim})")
    if g.answered is not None and g.answered[0] == msg.seq:
        return g.answered[1]
    g.wanted = (msg.seq, np.array(obs, np.float32))
    return None


def group_ready(g: LockstepGroup, runs: dict[str, LearnerRun], seq: int) -> bool:
    """Every run of the group has its steps before `seq` in replay and learnt. A run
    already past `seq` (an actor restarted between publishing one run's step and
    another's) does not hold the answer: that step comes again as a duplicate."""
    for run in g.runs:
        st = runs.get(run)
        if st is None:
            return False
        taken = st.intake.received.expected(g.actor)
        if taken > seq:
            continue
        if taken < seq or not st.intake.in_replay(g.actor, seq) or not learnt_up_to(st):
            return False
    return True


def group_answer(g: LockstepGroup, runs: dict[str, LearnerRun]) -> bytes | None:
    """The answer to the group's open request once it is ready: one `act` of the
    group's current weights for every run."""
    if g.wanted is None or not group_ready(g, runs, g.wanted[0]):
        return None
    seq, obs = g.wanted
    act = g.learner.act(obs[:, None])[:, 0].astype(np.float32)
    payload = encode(Action(g.runs[0], seq=seq, act=act))
    g.wanted, g.answered = None, (seq, payload)
    return payload
