"""The reward critic Q^r(s, a) of SAC/WCSAC (one network; the loss holds the twin)."""

from __future__ import annotations

from tensordict.utils import NestedKey
from torchrl.modules import ValueOperator

from wcsac_rl.modules._mlp import make_mlp

__all__ = ["make_qvalue"]


def make_qvalue(
    observation_dim: int,
    action_dim: int,
    *,
    observation_key: NestedKey = "observation",
    action_key: NestedKey = "action",
    out_key: NestedKey = "state_action_value",
    width: int = 256,
    depth: int = 2,
    activation: str = "relu",
) -> ValueOperator:
    """One state-action value network ``Q(s, a)`` writing ``state_action_value``.

    Pass a list of independently initialised copies to the loss for the twin critic
    (``[make_qvalue(...) for _ in range(2)]``); a single module given to TorchRL's
    SAC loss is expanded with re-sampled weights instead.

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> q = make_qvalue(44, 2)
        >>> td = TensorDict({"observation": torch.randn(3, 44), "action": torch.rand(3, 2)}, [3])
        >>> q(td)["state_action_value"].shape
        torch.Size([3, 1])
    """
    net = make_mlp(observation_dim + action_dim, 1, width=width, depth=depth, activation=activation)
    return ValueOperator(net, in_keys=[observation_key, action_key], out_keys=[out_key])
