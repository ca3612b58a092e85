"""The learners: one `Learner` protocol, three ways to run the same MADDPG update.

* reference.py: `MADDPG`, one plain PyTorch update per agent (the definition);
* batched.py: `BatchedMADDPG`, the same update with all agents in stacked products
  (layers.py, the update itself in `StackedMADDPG`) and its minibatch optionally split
  over threads (lanes.py);
* group.py: `GroupMADDPG`, R runs' batched updates as one (the same `StackedMADDPG`
  over R x N stack entries);
* runs.py: `RunsLearner`, what the trainer needs of R runs' learners, and `SoloRuns`,
  any one `Learner` as a group of one;
* tuning.py: `TunedMADDPG`, a `BatchedMADDPG` whose threads a tuner picks per block
  of updates (`learner_lanes: auto`);
* checkpoint.py: the batched storage in the reference's checkpoint format;
* precision.py: fp32 or bf16 matrix products for the batched learner, and whether the
  CPU runs bf16 natively.

shared/run/factories.py builds the one a config asks for.
"""

from shared.core.learners.base import (
    ALGOS,
    AgentDims,
    Learner,
    LearnerSpec,
    agent_slice,
    check_agents,
)
from shared.core.learners.batched import BatchedMADDPG
from shared.core.learners.lanes import Lanes, LaneTuner
from shared.core.learners.precision import PRECISIONS
from shared.core.learners.reference import MADDPG
from shared.core.learners.runs import RunsLearner, SoloRuns
from shared.core.learners.tuning import AUTO_MODES, TunedMADDPG

__all__ = [
    "ALGOS",
    "AUTO_MODES",
    "MADDPG",
    "PRECISIONS",
    "RunsLearner",
    "SoloRuns",
    "AgentDims",
    "BatchedMADDPG",
    "LaneTuner",
    "Lanes",
    "Learner",
    "LearnerSpec",
    "TunedMADDPG",
    "agent_slice",
    "check_agents",
]
