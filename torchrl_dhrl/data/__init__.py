"""Replay-buffer relabelling for both DHRL levels.

* :class:`RelabelReplayBuffer`: a replay buffer whose ``sample()`` returns relabelled batches (it runs
  the relabellers below with the sampled storage indices).
* :class:`FutureGoalRelabel`: hindsight goals from the future of the same episode (both levels; writes
  the policy-critic and graph-critic goal / reward pairs from one low-level sample).
* :class:`HighLevelTransitionBuilder`: high-level transitions, one per issued subgoal, from collected
  low-level trajectories.
* :class:`HindsightSubgoalRelabel`: HAC hindsight actions, subgoal testing and the gradual penalty.
* :class:`CompactLazyTensorStorage`: a lazy tensor storage whose checkpoints hold only the written rows.
* :class:`SparseGoalReward`: the sparse ``-1`` / ``0`` goal reward both levels train on.
"""

from torchrl_dhrl.data.future_goals import FutureGoalRelabel
from torchrl_dhrl.data.high_level_transitions import HighLevelTransitionBuilder
from torchrl_dhrl.data.relabel_buffer import RelabelReplayBuffer
from torchrl_dhrl.data.rewards import SparseGoalReward
from torchrl_dhrl.data.storage import CompactLazyTensorStorage
from torchrl_dhrl.data.subgoal_relabel import HindsightSubgoalRelabel

__all__ = [
    "CompactLazyTensorStorage",
    "FutureGoalRelabel",
    "HighLevelTransitionBuilder",
    "HindsightSubgoalRelabel",
    "RelabelReplayBuffer",
    "SparseGoalReward",
]
