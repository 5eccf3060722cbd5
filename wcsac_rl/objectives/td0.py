"""The reward critic's TD(0) target, computed directly where TorchRL's estimator would
do nothing more than ``r + γ (1 − term) V(s')``."""

from __future__ import annotations

from tensordict import TensorDictBase
from torch import Tensor
from torchrl.objectives.value import TD0Estimator

__all__ = ["td0_target"]


def td0_target(estimator: TD0Estimator, tensordict: TensorDictBase, next_value: Tensor) -> Tensor:
    """TorchRL's TD(0) estimate ``r + γ (1 − term) V(s')``, shaped like the reward.

    Computed here when the estimator has nothing beyond plain TD(0) to apply (no
    reward standardisation, no multi-step ``steps_to_next_obs``): the same elementwise
    operations in the same order, without the estimator's tensordict round trip.
    Otherwise, or when the shapes do not line up, the estimator does it (and reports
    errors).
    """
    keys = estimator.tensor_keys
    reward = tensordict.get(("next", keys.reward), None)
    terminated = tensordict.get(("next", keys.terminated), None)
    if terminated is None:
        terminated = tensordict.get(("next", keys.done), None)
    if (
        estimator.average_rewards
        or reward is None
        or terminated is None
        or tensordict.get(keys.steps_to_next_obs, None) is not None
        or not reward.shape == terminated.shape == next_value.shape
    ):
        td_value = tensordict.clone(False)
        td_value.set(("next", keys.value), next_value)
        return estimator.value_estimate(td_value)
    gamma = estimator.gamma.to(reward.device)
    return reward + gamma * (~terminated).int() * next_value
