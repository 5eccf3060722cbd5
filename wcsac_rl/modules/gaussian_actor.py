"""CPO's networks: a diagonal-Gaussian actor with a state-independent log-std, and V(s).

The on-policy trust-region references (Achiam's CPO code, OpenAI's
safety-starter-agents, OmniSafe) use an *unsquashed* Gaussian whose mean is an MLP
of the observation and whose log-std is a free parameter vector (initialised to
−0.5 in safety-starter-agents). Sampled actions are not clipped by the policy: the
environment clips them (every env of this kit clips to ``[-1, 1]``), so the stored
action is the one whose log-probability the policy gradient uses.
"""

from __future__ import annotations

from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import TensorSpec
from torchrl.envs.utils import ExplorationType
from torchrl.modules import IndependentNormal, ProbabilisticActor, ValueOperator

from wcsac_rl.modules._mlp import make_mlp

__all__ = ["make_gaussian_actor", "make_state_value"]


def make_gaussian_actor(
    observation_dim: int,
    action_spec: TensorSpec,
    *,
    observation_key: NestedKey = "observation",
    action_key: NestedKey = "action",
    width: int = 256,
    depth: int = 2,
    activation: str = "tanh",
    log_std_init: float = -0.5,
) -> ProbabilisticActor:
    """Build a diagonal Gaussian policy ``N(μ_θ(s), diag(exp(2 log σ)))`` with a free log σ.

    Args:
        observation_dim: size of the (flat) observation.
        action_spec: the env's (unbatched) action spec; its last dimension is the
            action size. It is attached to the actor for the collector, but actions
            are *not* projected onto it (the env clips).

    Keyword Args:
        observation_key: key read by the policy.
        action_key: key the sampled action is written to.
        width, depth, activation: shape of the mean MLP (safety-starter-agents'
            Safety Gym runs: 2 × 256, tanh).
        log_std_init: initial value of every log σ (safety-starter-agents: −0.5).

    Returns:
        A ``ProbabilisticActor`` writing ``loc``, ``scale`` and ``action_key``; under
        ``ExplorationType.DETERMINISTIC`` the action is the mean ``loc``.

    Example:
        >>> import torch
        >>> from torchrl.data import Bounded
        >>> from tensordict import TensorDict
        >>> actor = make_gaussian_actor(6, Bounded(-1.0, 1.0, shape=(2,)), width=16)
        >>> td = actor(TensorDict({"observation": torch.randn(5, 6)}, [5]))
        >>> td["action"].shape, td["scale"][0]
        (torch.Size([5, 2]), tensor([0.6065, 0.6065], grad_fn=<SelectBackward0>))
    """
    action_dim = action_spec.shape[-1]
    net = nn.Sequential(
        make_mlp(observation_dim, action_dim, width=width, depth=depth, activation=activation),
        AddStateIndependentNormalScale(
            action_dim, scale_mapping="exp", init_value=float(log_std_init)
        ),
    )
    module = TensorDictModule(net, in_keys=[observation_key], out_keys=["loc", "scale"])
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=[action_key],
        spec=action_spec,
        distribution_class=IndependentNormal,
        default_interaction_type=ExplorationType.RANDOM,
        return_log_prob=False,
    )


def make_state_value(
    observation_dim: int,
    *,
    observation_key: NestedKey = "observation",
    out_key: NestedKey = "state_value",
    width: int = 256,
    depth: int = 2,
    activation: str = "tanh",
) -> ValueOperator:
    """A state-value network ``V(s)`` writing ``out_key`` (``[*B, 1]``).

    CPO uses two: ``V^r`` (``"state_value"``) and ``V^c`` (``"state_cost_value"``).

    Example:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> v = make_state_value(6, out_key="state_cost_value", width=16)
        >>> v(TensorDict({"observation": torch.randn(3, 6)}, [3]))["state_cost_value"].shape
        torch.Size([3, 1])
    """
    net = make_mlp(observation_dim, 1, width=width, depth=depth, activation=activation)
    return ValueOperator(net, in_keys=[observation_key], out_keys=[out_key])
