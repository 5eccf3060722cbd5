"""The loss's critics evaluated together: the twin reward critic and the safety head.

WCSAC reads every critic at the same state-actions three times per update (the target
networks at ``(s', a')``, the online ones at the replay ``(s, a)``, the detached
online ones at ``(s, a ~ π)``). :class:`Critics` does each reading in one call, on the
paths the loss's :class:`~wcsac_rl.objectives.fast_paths.FastPaths` took: one batched
ensemble evaluation (``FusedCritics``, which the safety head plans), else the reward
critics from their stacked parameters or through TorchRL's vmapped call and the safety
critic through its head (:mod:`wcsac_rl.objectives.safety_head`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import Tensor

from wcsac_rl.objectives.fast_paths import FastPaths, Layers, evaluate_stacked_mlp
from wcsac_rl.objectives.safety_head import SafetyHead, SafetyValues

__all__ = ["CriticParams", "CriticValues", "Critics"]


class CriticParams(NamedTuple):
    """The reward critics' and the safety critic's parameters for one evaluation;
    ``target`` marks the target networks (an IQN critic then draws N' fractions)."""

    qvalue: TensorDictBase
    safety: TensorDictBase
    target: bool = False


class CriticValues(NamedTuple):
    """Every critic at one batch of state-actions: the reward critics ``qvalue``
    ``[num_qvalue_nets, *B]`` (``None`` where they were not read) and the safety
    critic's :class:`~wcsac_rl.objectives.safety_head.SafetyValues`."""

    qvalue: Tensor | None
    safety: SafetyValues

    def detach(self) -> CriticValues:
        """The same values without gradient."""
        qvalue = None if self.qvalue is None else self.qvalue.detach()
        return CriticValues(qvalue, self.safety.detach())


class Critics:
    """The reward critics and the safety head, read together.

    Args:
        qvalue_network (TensorDictModule): the reward critic (the loss's module, called
            with stacked parameters through ``vmap_qvalue``).
        head (SafetyHead): the safety critic's head.
        keys: the loss's ``tensor_keys`` (``action``, ``state_action_value``).
        paths (FastPaths): the loss's fast paths (its ``fused`` and ``stacked`` readings).
    """

    def __init__(
        self, qvalue_network: TensorDictModule, head: SafetyHead, keys, paths: FastPaths
    ) -> None:
        self.qvalue_network, self.head, self.keys, self.paths = qvalue_network, head, keys, paths

    fused = property(lambda self: self.paths.fused)
    stacked = property(lambda self: self.paths.stacked)

    def read_through_modules(self) -> None:
        """:meth:`FastPaths.read_through_modules`."""
        self.paths.read_through_modules()

    def layers(self, params: CriticParams) -> Layers | None:
        """The fused critics' stacked parameters (``None`` when not fused): gather them
        once to read the critics several times with the same parameters."""
        if self.fused is None:
            return None
        return self.fused.layers(params.qvalue, params.safety)

    def values(
        self,
        tensordict: TensorDictBase,
        action: Tensor,
        params: CriticParams,
        vmap_qvalue: Callable,
        layers: Layers | None = None,
        *,
        qvalue: bool = True,
    ) -> CriticValues:
        """Every critic with ``params`` at the state of ``tensordict`` and ``action``
        (``layers``: already gathered from ``params``); ``qvalue=False`` reads the
        safety critic alone (``qvalue`` is then ``None``: nothing is evaluated for it)."""
        if self.fused is not None:
            observation = tensordict.get(self.qvalue_network.in_keys[0])
            layers = self.layers(params) if layers is None else layers
            q, mean, variance = self.fused.values(observation, action, layers, qvalue=qvalue)
            return CriticValues(q, SafetyValues(mean, variance))
        q = self._qvalue(tensordict, action, params, vmap_qvalue) if qvalue else None
        safety = self.head.values(tensordict, params.safety, action, target=params.target)
        return CriticValues(q, safety)

    def target_values(
        self,
        next_states: TensorDictBase,
        next_action: Tensor,
        params: CriticParams,
        vmap_qvalue: Callable,
        ahead: TensorDictBase | None,
        sample: Callable[[TensorDictBase], Tensor],
    ) -> CriticValues:
        """The target critics for the TD targets: the reward critics at ``(s', a')``
        and the safety critic where its target bootstraps — at ``(s', a')`` when
        ``ahead`` is ``None``, else at the n-step states ``ahead`` and the action
        ``sample(ahead)`` (``a ~ π``).

        With ``ahead`` the safety critic is not read at ``(s', a')`` by an unfused
        critic; a head whose readings draw random numbers (the IQN's fractions) draws
        there what that reading drew, without evaluating the critic, so the random
        stream, and every result, is that of the reading it made before. Fused critics
        keep the one batched product over every member at ``(s', a')``: evaluating fewer
        members, or the safety pair at ``ahead`` in the same product, rounds differently,
        and the risky-detour learning test showed that training outcomes are not robust
        to it. ``sample`` is called after ``a'`` was
        drawn and after the reward critics (the order the targets always drew)."""
        if ahead is None:
            return self.values(next_states, next_action, params, vmap_qvalue)
        if self.fused is not None:
            # the reward critics from the same batched product over every member as
            # always (a product over fewer members, or with the safety pair at s_{t+m},
            # rounds differently, and training results are not robust to that), the
            # safety critic at s_{t+m} through its own network
            observation = next_states.get(self.qvalue_network.in_keys[0])
            q, _, _ = self.fused.values(observation, next_action, self.layers(params))
        else:
            q = self._qvalue(next_states, next_action, params, vmap_qvalue)
        self.head.skip_reading(params.safety, target=params.target)
        safety = self.head.values(ahead, params.safety, sample(ahead), target=params.target)
        return CriticValues(q, safety)

    def _qvalue(self, tensordict, action, params: CriticParams, vmap_qvalue) -> Tensor:
        """The reward critics, ``[num_qvalue_nets, *B]``: TorchRL's vmapped call, or
        its kernels read straight from the stacked parameters (the same values)."""
        if self.stacked is not None:
            observation = tensordict.get(self.qvalue_network.in_keys[0])
            x = torch.cat([observation, action], dim=-1)
            return evaluate_stacked_mlp(x, params.qvalue, self.stacked).squeeze(-1)
        td_q = tensordict.select(*self.qvalue_network.in_keys, strict=False)
        td_q.set(self.keys.action, action)
        return vmap_qvalue(td_q, params.qvalue).get(self.keys.state_action_value).squeeze(-1)
