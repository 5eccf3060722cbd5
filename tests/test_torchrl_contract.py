"""TorchRL's own SACLoss / LossModule test cases, ported to WCSACLoss and SACLagLoss.

Ported from pytorch/rl at the 0.14.0 release commit 373c31a85 (``prepare-0.14``; the
installed 0.14.1 has the same ``torchrl/objectives/sac.py``):
``test/objectives/test_sac.py::TestSAC`` (losses independent, list of q-value nets and
``SoftUpdate``, state dict, ``separate_losses`` with a shared trunk, the ``MultiStep``
batcher, tensordict keys, no-tensordict calls, ``skip_done_states``, target entropy,
reduction, prioritized weights, ``deactivate_vmap``) and
``test/objectives/test_loss_module.py`` (``TestLossMaskReduction``, ``TestBuffer`` casts,
``test_loss_exploration``, ``TestMakeValueEstimator``, value-estimator key forwarding),
plus ``test/compile`` (``fullgraph=True``).

Every case runs on a grid of *variants*: loss class (``WCSACLoss`` at α = 0.5,
``SACLagLoss``) × safety critic (``kit``: the kit's actor and critics, taking the loss's
fast paths; ``user``: TorchRL-style ``ProbabilisticActor`` / ``ValueOperator`` and a plain
``TensorDictModule`` with mean and variance heads) × options (``paper``:
``PAPER_OPTIONS``, the loss's own defaults; ``study``: the StaticEnv study's safety critic
and κ reads that the kit's recipes use, fed by the kit's ``NStepCost`` and
``StartStateBuffer`` as a TorchRL user's pipeline would; the kit's recipe adds the episode
signal of ``EpisodeCostWindow``). Where a case's assertion is
not obvious for a safe loss, TorchRL's ``SACLoss`` runs the same assertion first
(``reference``), so the ported test is shown to pass on the loss it was written for.

Every case runs; nothing is skipped or marked xfail. The defects these cases found are
named where their cases are (D1 in_keys, D2 ``skip_done_states``, D3 ``separate_losses``,
D4 value estimators, D5 ``MultiStep``, D7 masking, D9 a batch without ``terminated``,
the plain first batch).
"""

from __future__ import annotations

import functools
import warnings
from copy import deepcopy
from pathlib import Path

import pytest
import torch
from _loss_helpers import STUDY_OPTIONS, recipe_kwargs
from _tolerance import assert_close_f32
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import (
    CompositeDistribution,
    NormalParamExtractor,
    set_composite_lp_aggregate,
)
from tensordict.nn import ProbabilisticTensorDictModule as ProbMod
from tensordict.nn import ProbabilisticTensorDictSequential as ProbSeq
from tensordict.nn import TensorDictModule as Mod
from tensordict.nn import TensorDictSequential as Seq
from torch import nn
from torchrl.data import (
    Bounded,
    Composite,
    Unbounded,
)
from torchrl.data.postprocs.postprocs import MultiStep
from torchrl.envs.utils import ExplorationType, exploration_type, set_exploration_type
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator
from torchrl.objectives import SACLoss, SoftUpdate, ValueEstimators
from torchrl.objectives.value import TD0Estimator

from wcsac_rl import SACLagLoss, WCSACLoss, make_actor, make_qvalue, make_safety_critic
from wcsac_rl.objectives import (
    PAPER_OPTIONS,
    EpisodeCostWindow,
    NStepCost,
    SingleGroupWarning,
    StartStateBuffer,
    param_groups,
    per_step_cost_threshold,
)
from wcsac_rl.objectives.inputs import collected_keys, missing_inputs, state_keys
from wcsac_rl.objectives.risk import gaussian_mixture_cvar, quantile_mixture_cvar

OBS, ACT = 3, 4
BATCH, TIME = 4, 6  # [envs, time] as a collector hands them over


@pytest.fixture(autouse=True)
def _composite_log_prob():
    # TorchRL's LossModuleTestBase runs every SAC case under this setting
    setter = set_composite_lp_aggregate(False)
    setter.set()
    yield
    setter.unset()


# ----------------------------------------------------------------------- builders
class UserSafetyCritic(nn.Module):
    """A user's own Gaussian safety critic: a mean head and a softplus variance head."""

    def __init__(self, in_features: int = OBS + ACT, hidden: int | None = None) -> None:
        super().__init__()
        self.mean = nn.Linear(in_features, 1)
        self.variance = nn.Linear(in_features, 1)

    def forward(self, observation, action):
        if isinstance(action, TensorDictBase):
            action = action.get("action1")
        x = torch.cat([observation, action], -1)
        return self.mean(x), nn.functional.softplus(self.variance(x)) + 1e-3


class UserQValue(nn.Module):
    """TorchRL's ``_create_mock_qvalue`` module."""

    def __init__(self) -> None:
        super().__init__()
        self.linear = nn.Linear(OBS + ACT, 1)

    def forward(self, obs, act):
        if isinstance(act, TensorDictBase):
            act = act.get("action1")
        return self.linear(torch.cat([obs, act], -1))


def user_actor(observation_key="observation", action_key="action", composite=False):
    """TorchRL's ``_create_mock_actor``: a ``ProbabilisticActor`` with a ``TanhNormal``."""
    spec = Bounded(-torch.ones(ACT), torch.ones(ACT), (ACT,))
    if composite:
        spec = Composite({action_key: {"action1": spec}})
        dist = functools.partial(CompositeDistribution, distribution_map={"action1": TanhNormal})
        module_out = [("params", "action1", "loc"), ("params", "action1", "scale")]
        actor_in = ["params"]
    else:
        dist, module_out = TanhNormal, ["loc", "scale"]
        actor_in = module_out
    net = nn.Sequential(nn.Linear(OBS, 2 * ACT), NormalParamExtractor())
    module = Mod(net, in_keys=[observation_key], out_keys=module_out)
    actor = ProbabilisticActor(
        module=module, distribution_class=dist, in_keys=actor_in, out_keys=[action_key], spec=spec
    )
    return actor, spec


def user_qvalue(observation_key="observation", action_key="action"):
    return ValueOperator(
        UserQValue(), in_keys=[observation_key, action_key], out_keys=["state_action_value"]
    )


def user_safety(observation_key="observation", action_key="action", out_keys=None):
    return Mod(
        UserSafetyCritic(),
        in_keys=[observation_key, action_key],
        out_keys=out_keys or ["cost_value", "cost_variance"],
    )


VARIANTS = [
    pytest.param((cls, critic, options), id=f"{cls}-{critic}-{options}")
    for cls in ("WCSAC", "SACLag")
    for critic in ("kit", "user")
    for options in ("paper", "study")
]


def options_of(name: str) -> dict:
    """The variant's recipe: the paper's, or the study's reads (the kit's recipe but for
    its episode signal, ``KIT_OPTIONS``' ``kappa_signal="max"``)."""
    return dict(PAPER_OPTIONS) if name == "paper" else dict(STUDY_OPTIONS)


def make_variant(variant, seed: int = 0, **kwargs):
    """The loss of ``variant`` = (class, critic, options), with ``kwargs`` on top (flat
    options change the variant's recipe: ``recipe_kwargs``)."""
    cls_name, critic, options = variant
    torch.manual_seed(seed)
    kwargs = recipe_kwargs(base=options_of(options), **kwargs)
    cls = WCSACLoss if cls_name == "WCSAC" else SACLagLoss
    if cls is WCSACLoss:
        kwargs.setdefault("risk_level", 0.5)
    if critic == "kit":
        actor = make_actor(OBS, Bounded(-1.0, 1.0, shape=(ACT,)), width=8)
        n = kwargs.pop("num_qvalue_nets", 2)
        qvalues = [make_qvalue(OBS, ACT, width=8) for _ in range(n)]
        safety = make_safety_critic(OBS, ACT, width=8, variance=cls is WCSACLoss)
        return cls(actor, qvalues, safety, num_qvalue_nets=n, **kwargs)
    actor, spec = user_actor()
    return cls(actor, user_qvalue(), user_safety(), action_spec=spec, **kwargs)


def make_sac(seed: int = 0, **kwargs) -> SACLoss:
    """TorchRL's SACLoss on the user-built actor and critic: the reference."""
    torch.manual_seed(seed)
    actor, spec = user_actor()
    return SACLoss(actor, user_qvalue(), action_spec=spec, **kwargs)


def trajectories(seed: int = 0, batch: int = BATCH, time: int = TIME, composite=False):
    """``[batch, time]`` collected steps: episodes of 3 steps (``step_count``), a cost and a
    termination at each episode's last step in the even envs, a truncation in the odd."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.randn(batch, time + 1, OBS, generator=g)
    step = (torch.arange(time) % 3).expand(batch, time).unsqueeze(-1).clone()
    done = step == 2
    terminated = done.clone()
    terminated[1::2] = False
    action = torch.rand(batch, time, ACT, generator=g) * 2 - 1
    td = TensorDict(
        {
            "observation": obs[:, :time].clone(),
            "action": TensorDict({"action1": action}, [batch, time]) if composite else action,
            "step_count": step,
            "next": {
                "observation": obs[:, 1:].clone(),
                "reward": torch.randn(batch, time, 1, generator=g),
                "cost": torch.bernoulli(torch.full((batch, time, 1), 0.4), generator=g),
                "done": done,
                "terminated": terminated,
            },
        },
        [batch, time],
        names=[None, "time"],
    )
    return td


def prepare(loss, traj: TensorDictBase, seed: int = 0, **nstep_keys) -> TensorDictBase:
    """A flat replay batch for ``loss``, through the kit's transforms its options need
    (a TorchRL user's pipeline: collector postproc, start-state buffer);
    ``nstep_keys``: ``NStepCost``'s ``done_key`` / ``terminated_key`` if renamed."""
    traj = traj.clone()
    if loss.cost_n_steps > 1:
        keys = list(loss.initial_state_keys)
        traj = NStepCost(loss.cost_n_steps, loss.cost_gamma, observation_keys=keys, **nstep_keys)(
            traj
        )
    flat = traj.reshape(-1)
    if loss.kappa_states == "initial":
        starts = StartStateBuffer.for_loss(loss)
        starts.add_starts(traj)
        torch.manual_seed(seed)
        flat = starts.attach(flat)
    if loss.kappa_signal != "critic":  # (no episode has finished yet: NaN, the critic's)
        flat = EpisodeCostWindow.for_loss(loss).attach(flat)
    return flat


def batch_for(loss, seed: int = 0, **kwargs) -> TensorDictBase:
    return prepare(loss, trajectories(seed, **kwargs), seed)


def loss_terms(out: TensorDictBase) -> list[str]:
    return [k for k in out.keys() if k.startswith("loss_")]


def total(out: TensorDictBase) -> torch.Tensor:
    return sum(out[k].sum() for k in loss_terms(out))


def groups_of(loss) -> dict[str, list[torch.nn.Parameter]]:
    """The loss's trainable parameters by owner."""
    groups = {
        "actor": list(loss.actor_network_params.values(True, True)),
        "qvalue": list(loss.qvalue_network_params.values(True, True)),
        "alpha": [loss.log_alpha],
    }
    if isinstance(loss, WCSACLoss):
        safety = loss.safety_network_params.flatten_keys(".")
        # the mean and the variance heads: each has its own TD loss
        groups["safety_mean"] = [p for k, p in safety.items() if "variance" not in k]
        groups["safety_variance"] = [p for k, p in safety.items() if "variance" in k]
        if loss.kappa_rule == "gradient":
            groups["kappa"] = [loss.kappa_raw]
    return groups


def no_grad(params) -> bool:
    return all(p.grad is None or (p.grad == 0).all() for p in params)


def all_grad(params) -> bool:
    return not any(p.grad is None or (p.grad == 0).all() for p in params)


class check_td_steady:
    """TorchRL's ``_check_td_steady``: the loss modifies no entry it was given."""

    def __init__(self, td):
        self.td, self.clone = td, td.clone()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if exc[0] is None:
            for key in self.clone.keys(True, True):
                torch.testing.assert_close(self.td.get(key), self.clone.get(key), msg=str(key))


# which parameter groups each loss term may reach (TestSAC's "losses are independent")
OWNERS = {
    "loss_actor": "actor",
    "loss_qvalue": "qvalue",
    "loss_alpha": "alpha",
    "loss_cost_value": "safety_mean",
    "loss_cost_variance": "safety_variance",
    "loss_kappa": "kappa",
}


# --------------------------------------------------------------- TestSAC: test_sac
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("delay_qvalue", [True, False])
def test_losses_are_independent_and_reach_every_parameter(variant, delay_qvalue):
    loss = make_variant(variant, delay_qvalue=delay_qvalue)
    td = batch_for(loss)
    with check_td_steady(td):
        out = loss(td)
    assert loss.tensor_keys.priority in td.keys()
    groups = groups_of(loss)
    for key in loss_terms(out):
        out[key].sum().backward(retain_graph=True)
        for name, params in groups.items():
            if name == OWNERS[key]:
                assert all_grad(params), f"{key} does not reach {name}"
            else:
                assert no_grad(params), f"{key} reaches {name}"
        loss.zero_grad()
    total(out).backward()
    named = list(loss.named_parameters())
    assert len({p for _, p in named}) == len(named)
    buffers = list(loss.named_buffers())
    assert len({b for _, b in buffers}) == len(buffers)
    for name, p in named:
        if name.startswith("target_"):
            assert p.grad is None or p.grad.norm() == 0.0, name
        else:
            assert p.grad is not None and p.grad.norm() > 0.0, name


# ------------------------------------------- TestSAC: test_sac_list_qvalue_networks
@pytest.mark.parametrize("variant", VARIANTS)
def test_soft_update_moves_every_target_including_the_safety_critics(variant):
    loss = make_variant(variant)
    loss(batch_for(loss))
    updater = SoftUpdate(loss, eps=0.5)
    targets_before = updater._targets.clone()
    assert any("safety" in str(k) for k in updater._targets.keys(True, True))
    with torch.no_grad():
        for source in updater._sources.values(True, True):
            source.add_(1)
    updater.step()
    for key, target in updater._targets.items(True, True):
        torch.testing.assert_close(target, targets_before.get(key) + 0.5)


# ---------------------------------------- TestSAC: test_sac_state_dict / test_state_dict
@pytest.mark.parametrize("variant", VARIANTS)
def test_state_dict_loads_into_a_fresh_loss(variant):
    loss = make_variant(variant)
    loss.target_entropy  # noqa: B018  (TorchRL's "with an access in between")
    with torch.no_grad():
        for p in loss.parameters():
            p.add_(0.25)
    state = loss.state_dict()
    fresh = make_variant(variant, seed=1)
    fresh.load_state_dict(state)
    for key, value in fresh.state_dict().items():
        torch.testing.assert_close(value, state[key], msg=key)


# ---------------------------------------------- test_reset_parameters_recursive
@pytest.mark.parametrize("variant", VARIANTS)
def test_reset_parameters_recursive(variant):
    loss = make_variant(variant)
    names = ["actor_network_params", "qvalue_network_params", "safety_network_params"]
    old = {}
    for name in names:
        params = getattr(loss, name)
        with torch.no_grad():
            params.apply_(lambda p: p.add_(1000))
        old[name] = params.clone()
    loss.reset_parameters_recursive()
    for name in names:
        for key, value in getattr(loss, name).items(True, True):
            assert (value != old[name].get(key)).any(), (name, key)


# ------------------------------------------------- TestSAC: test_sac_separate_losses
def shared_trunk_setup(composite=False, n_hidden=2):
    """TorchRL's ``_create_mock_common_layer_setup``, with a safety head on the trunk too."""

    class Head(nn.Module):
        def __init__(self, outputs: int = 1) -> None:
            super().__init__()
            self.linear1 = nn.Linear(n_hidden + ACT, n_hidden)
            self.linear2 = nn.Linear(n_hidden, outputs)

        def forward(self, hidden, act):
            if isinstance(act, TensorDictBase):
                act = act.get("action1")
            out = self.linear2(torch.relu(self.linear1(torch.cat([hidden, act], -1))))
            if out.shape[-1] == 1:
                return out
            mean, raw = out.chunk(2, -1)
            return mean, nn.functional.softplus(raw) + 1e-3

    common = Mod(
        MLP(num_cells=4, in_features=OBS, depth=3, out_features=n_hidden), ["obs"], ["hidden"]
    )
    actor_net = MLP(num_cells=4, in_features=n_hidden, depth=1, out_features=2 * ACT)
    if composite:
        dist = functools.partial(CompositeDistribution, distribution_map={"action1": TanhNormal})
        module_out, actor_in = (
            [("params", "action1", "loc"), ("params", "action1", "scale")],
            ["params"],
        )
    else:
        dist, module_out = TanhNormal, ["loc", "scale"]
        actor_in = module_out
    actor = ProbSeq(
        common,
        Mod(actor_net, in_keys=["hidden"], out_keys=["param"]),
        Mod(NormalParamExtractor(), in_keys=["param"], out_keys=module_out),
        ProbMod(in_keys=actor_in, out_keys=["action"], distribution_class=dist),
    )
    qvalue = Seq(common, Mod(Head(), in_keys=["hidden", "action"], out_keys=["state_action_value"]))
    safety = Seq(
        common,
        Mod(Head(2), in_keys=["hidden", "action"], out_keys=["cost_value", "cost_variance"]),
    )
    return actor, qvalue, safety, common


def shared_trunk_batch(composite=False, batch=8):
    g = torch.Generator().manual_seed(3)
    action = torch.rand(batch, ACT, generator=g) * 2 - 1
    return TensorDict(
        {
            "obs": torch.randn(batch, OBS, generator=g),
            "action": {"action1": action} if composite else action,
            "next": {
                "obs": torch.randn(batch, OBS, generator=g),
                "reward": torch.randn(batch, 1, generator=g),
                "cost": torch.bernoulli(torch.full((batch, 1), 0.5), generator=g),
                "done": torch.zeros(batch, 1, dtype=torch.bool),
                "terminated": torch.zeros(batch, 1, dtype=torch.bool),
            },
        },
        [batch],
    )


def assert_separate_losses(loss, out, common, separate_losses, critics):
    trunk = len(list(common.parameters()))
    for key in loss_terms(out):
        out[key].sum().backward(retain_graph=True)
        owner = OWNERS[key].split("_")[0]  # safety_mean -> safety
        if owner == "actor":
            for name in critics:
                assert no_grad(getattr(loss, f"{name}_network_params").values(True, True)), (
                    key,
                    name,
                )
            assert all_grad(loss.actor_network_params.values(True, True))
        elif owner in critics:
            assert no_grad(loss.actor_network_params.values(True, True)), key
            params = list(getattr(loss, f"{owner}_network_params").values(True, True))
            if separate_losses:
                assert no_grad(params[:trunk]), f"{key} trains the shared trunk"
                assert all_grad(params[trunk:]), f"{key} misses its head"
            else:
                assert all_grad(params), key
        else:
            assert no_grad(loss.actor_network_params.values(True, True)), key
            for name in critics:
                assert no_grad(getattr(loss, f"{name}_network_params").values(True, True)), key
        loss.zero_grad()


@pytest.mark.parametrize("separate_losses", [False, True])
@pytest.mark.parametrize("composite", [False, True])
def test_separate_losses_reference(separate_losses, composite):
    """The assertions below, on TorchRL's SACLoss (without a safety head)."""
    torch.manual_seed(0)
    actor, qvalue, _, common = shared_trunk_setup(composite)
    loss = SACLoss(
        actor,
        qvalue,
        action_spec=Unbounded(shape=(ACT,)),
        num_qvalue_nets=1,
        separate_losses=separate_losses,
    )
    out = loss(shared_trunk_batch(composite))
    assert_separate_losses(loss, out, common, separate_losses, ["qvalue"])


# D3: the safety critic shares the actor's trunk as SACLoss's reward critic does (with
# separate_losses it reads the actor's tensors untrained; without, it trains its own copy)
SEPARATE_LOSSES_CASES = [
    pytest.param(
        cls,
        options,
        separate,
        composite,
        id=f"{cls}-{options}-separate={separate}-composite={composite}",
    )
    for cls in ("WCSAC", "SACLag")
    for options in ("paper", "study")
    for separate in (False, True)
    for composite in (False, True)
]


@pytest.mark.parametrize("cls,options,separate_losses,composite", SEPARATE_LOSSES_CASES)
def test_separate_losses_with_a_shared_trunk(cls, options, separate_losses, composite):
    torch.manual_seed(0)
    actor, qvalue, safety, common = shared_trunk_setup(composite)
    loss_cls = WCSACLoss if cls == "WCSAC" else SACLagLoss
    kwargs = recipe_kwargs(base=options_of(options), kappa_states="replay", cost_n_steps=1)
    if cls == "WCSAC":
        kwargs["risk_level"] = 0.5
    loss = loss_cls(
        actor,
        qvalue,
        safety,
        action_spec=Unbounded(shape=(ACT,)),
        num_qvalue_nets=1,
        separate_losses=separate_losses,
        **kwargs,
    )
    trunk = {id(p) for p in common.parameters()}
    own = [p for p in loss.safety_network_params.values(True, True)]
    registered = {id(p) for p in loss.parameters()}
    if separate_losses:  # the actor's own tensors, read (not trained) by the safety critic
        shared = [p for p in own if any(p.data_ptr() == q.data_ptr() for q in common.parameters())]
        assert len(shared) == len(trunk) and not any(isinstance(p, nn.Parameter) for p in shared)
    else:  # its own trainable copy, equal to the trunk at the start
        assert not trunk & {id(p) for p in own}
        assert all(isinstance(p, nn.Parameter) and id(p) in registered for p in own)
        for p, q in zip(own, common.parameters(), strict=False):
            torch.testing.assert_close(p, q)
    out = loss(shared_trunk_batch(composite))
    assert_separate_losses(loss, out, common, separate_losses, ["qvalue", "safety"])


# --------------------------------------------------------- TestSAC: test_sac_batcher
def nstep_cost_target(loss, traj, n):
    """The n-step cost target of NStepCost's definition, for a safety critic that ignores
    the action: ``Σ_{k<m} γ_c^k c_{t+k} + γ_c^m (1 − stop) Q̄^c(s_{t+m})``."""
    ref = NStepCost(n, loss.cost_gamma)(traj.clone()).get("nstep")
    with torch.no_grad():
        td = ref.select("observation").set("action", torch.zeros(*ref.shape, ACT))
        with loss.target_safety_network_params.to_module(loss.safety_network):
            q_next = loss.safety_network(td).get(loss.tensor_keys.cost_value).squeeze(-1)
    if loss.nonnegative_cost:
        q_next = q_next.clamp(min=0)
    stop = ref.get("terminated" if loss.cost_bootstrap_truncated else "done").squeeze(-1)
    gamma = loss.cost_gamma ** ref.get("steps").to(torch.float32)
    return ref.get("cost").squeeze(-1) + gamma * (~stop).float() * q_next


# D5: MultiStep (n > 1) with a one-step cost target is refused in one line (the cost of
# one step would be bootstrapped from the state n steps on), MultiStep(n_steps=1) gives
# the raw batch's losses bit for bit (TestSAC.test_sac_batcher); the n-step cost entries
# (NStepCost, written before MultiStep) give the correct target
MULTISTEP_CASES = [
    pytest.param(cls, options, n, id=f"{cls}-{options}-n{n}")
    for cls in ("WCSAC", "SACLag")
    for options in ("paper", "study")
    for n in (1, 2, 3)
]


@pytest.mark.parametrize("cls,options,n", MULTISTEP_CASES)
def test_multistep_batches_are_correct_or_refused(cls, options, n):
    """TorchRL's MultiStep postproc in the collector: either the cost target has the same
    n-step look-ahead as the reward's, or the loss refuses the batch with one clear line."""
    loss = make_variant((cls, "user", options))
    loss.make_value_estimator(gamma=0.9)
    with torch.no_grad():  # a safety critic that ignores the action: exact targets
        for params in (loss.safety_network_params, loss.target_safety_network_params):
            params["module", "mean", "weight"][..., OBS:] = 0.0
    traj = trajectories()
    if loss.cost_n_steps > 1:  # the kit's n-step cost entries, written before MultiStep
        traj = NStepCost(loss.cost_n_steps, loss.cost_gamma)(traj)
    ms = MultiStep(gamma=0.9, n_steps=n)(traj.clone())
    assert (ms["steps_to_next_obs"] > 1).any() == (n > 1)
    flat = ms.reshape(-1)
    if loss.kappa_states == "initial":
        starts = StartStateBuffer.for_loss(loss)
        starts.add_starts(traj)
        flat = starts.attach(flat)
    if loss.cost_n_steps == 1 and n == 1:  # MultiStep(n_steps=1) is a no-op: accepted
        raw = traj.reshape(-1)
        if loss.kappa_states == "initial":
            raw = starts.attach(raw)
        outputs = []
        for batch in (raw, flat):
            torch.manual_seed(0)
            with check_td_steady(batch):
                outputs.append(loss(batch))
        assert set(outputs[0].keys()) == set(outputs[1].keys())
        for key, value in outputs[0].items():
            assert torch.equal(value, outputs[1][key]), key  # bit for bit, as SACLoss
        return
    if loss.cost_n_steps == 1:  # n > 1 with one-step cost targets: refused
        for call in (loss.compute_targets, loss):
            with check_td_steady(flat), pytest.raises(ValueError) as err:
                call(flat)
            message = err.value.args[0]
            assert "\n" not in message and "MultiStep" in message and "NStepCost" in message
            # (the way it names is one the constructor takes)
            assert "safety_head=SafetyHeadOptions(cost_n_steps=n)" in message
        return
    targets = loss.compute_targets(flat)
    expected = nstep_cost_target(loss, trajectories(), max(n, loss.cost_n_steps))
    assert_close_f32(targets["cost_target"], expected.reshape(-1), ops=16)
    with check_td_steady(flat):
        out = loss(flat)
    total(out).backward()
    for name, p in loss.named_parameters():
        assert name.startswith("target_") or p.grad is not None, name


def test_nstep_cost_refuses_a_batch_multistep_has_seen():
    """NStepCost reads each step's own cost and flags, which MultiStep replaces by those
    n steps on: after MultiStep it refuses in one line (before it, the case above)."""
    ms = MultiStep(gamma=0.9, n_steps=2)(trajectories())
    with pytest.raises(ValueError) as err:
        NStepCost(3, 1.0)(ms)
    assert "\n" not in err.value.args[0] and "before MultiStep" in err.value.args[0]
    # MultiStep(n_steps=1) changes nothing NStepCost reads: the same entries as without it
    traj = trajectories()
    once = NStepCost(3, 1.0)(MultiStep(gamma=0.9, n_steps=1)(traj.clone()))
    assert (once["nstep"] == NStepCost(3, 1.0)(traj.clone())["nstep"]).all()


def test_multistep_reference_changes_the_reward_target():
    """What the port checks on SACLoss: n = 1 leaves the batch and the loss unchanged,
    n > 1 changes the loss (TestSAC.test_sac_batcher)."""
    loss = make_sac()
    traj = trajectories()
    for n in (1, 3):
        ms = MultiStep(gamma=0.9, n_steps=n)(traj.clone())
        torch.manual_seed(0)
        with torch.no_grad():
            a = loss(traj.clone().reshape(-1))
        torch.manual_seed(0)
        with torch.no_grad():
            b = loss(ms.reshape(-1))
        same = torch.allclose(a["loss_qvalue"], b["loss_qvalue"])
        assert same == (n == 1)


# ------------------------------------------------- TestSAC: test_sac_tensordict_keys
@pytest.mark.parametrize("variant", VARIANTS)
def test_tensordict_keys(variant):
    loss = make_variant(variant)
    defaults = {
        "priority": "td_error",
        "value": "state_value",
        "state_action_value": "state_action_value",
        "action": "action",
        "log_prob": "action_log_prob",
        "reward": "reward",
        "done": "done",
        "terminated": "terminated",
        "cost": "cost",
        "cost_value": "cost_value",
        "cost_variance": "cost_variance",
        "initial_states": "initial",
        "nstep": "nstep",
        "episode_cvar": "episode_cvar",
    }
    fn = deepcopy(loss)
    with pytest.raises(ValueError):
        fn.set_keys(unknown_key="test2")
    for key, value in defaults.items():
        assert getattr(deepcopy(loss).tensor_keys, key) == value, key
    fn = deepcopy(loss)
    for key in defaults:
        fn.set_keys(**{key: "test1"})
        assert getattr(fn.tensor_keys, key) == "test1"
    # keys reach the value estimator (set_advantage_keys_through_loss_test)
    fn = deepcopy(loss)
    mapping = {
        "value": "state_value_test",
        "reward": "reward_test",
        "done": ("done", "test"),
        "terminated": ("terminated", "test"),
    }
    fn.set_keys(**mapping)
    fn.make_value_estimator(ValueEstimators.TD0)
    for key, value in mapping.items():
        assert getattr(fn.value_estimator.tensor_keys, key) == value


# ------------------------------------------- TestSAC: test_sac_notensordict / keys
KEY_CASES = [
    ("action", "observation", "reward", "done", "terminated"),
    ("action2", "observation2", "reward2", "done2", "terminated2"),
]


def renamed_variant(variant, action_key, observation_key):
    cls_name, critic, options = variant
    torch.manual_seed(0)
    cls = WCSACLoss if cls_name == "WCSAC" else SACLagLoss
    kwargs = recipe_kwargs(base=options_of(options))
    if cls is WCSACLoss:
        kwargs["risk_level"] = 0.5
    if critic == "kit":
        actor = make_actor(
            OBS,
            Bounded(-1.0, 1.0, shape=(ACT,)),
            width=8,
            observation_key=observation_key,
            action_key=action_key,
        )
        qvalues = [
            make_qvalue(OBS, ACT, width=8, observation_key=observation_key, action_key=action_key)
            for _ in range(2)
        ]
        safety = make_safety_critic(
            OBS,
            ACT,
            width=8,
            variance=cls is WCSACLoss,
            observation_key=observation_key,
            action_key=action_key,
        )
        return cls(actor, qvalues, safety, **kwargs)
    actor, spec = user_actor(observation_key, action_key)
    return cls(
        actor,
        user_qvalue(observation_key, action_key),
        user_safety(observation_key, action_key),
        action_spec=spec,
        **kwargs,
    )


def renamed_batch(loss, keys, seed=0):
    action_key, observation_key, reward_key, done_key, terminated_key = keys
    traj = trajectories(seed)
    renames = {
        "action": action_key,
        "observation": observation_key,
        ("next", "observation"): ("next", observation_key),
        ("next", "reward"): ("next", reward_key),
        ("next", "done"): ("next", done_key),
        ("next", "terminated"): ("next", terminated_key),
    }
    traj = traj.rename_key_(("next", "observation"), ("next", "obs_tmp"))
    traj = traj.rename_key_("observation", "obs_tmp")
    for old, new in renames.items():
        old = ("next", "obs_tmp") if old == ("next", "observation") else old
        old = "obs_tmp" if old == "observation" else old
        if old != new:
            traj.rename_key_(old, new)
    return prepare(loss, traj, seed, done_key=done_key, terminated_key=terminated_key)


def _flat_key(key) -> str:
    return key if isinstance(key, str) else "_".join(key)


# D1: in_keys list the start-state entries (("initial", obs)) kappa_states="initial" reads
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("keys", KEY_CASES, ids=["default-keys", "renamed-keys"])
def test_in_keys_list_every_entry_the_loss_reads(variant, keys):
    """``loss.in_keys`` is what a TorchRL pipeline keeps (``batch.select(*loss.in_keys)``):
    the loss must work on that selection, and every in_key must be one the batch has."""
    loss = renamed_variant(variant, keys[0], keys[1])
    loss.set_keys(reward=keys[2], done=keys[3], terminated=keys[4])
    td = renamed_batch(loss, keys)
    missing = [k for k in loss.in_keys if k not in td.keys(True, True)]
    assert not missing, f"in_keys the pipeline does not write: {missing}"
    torch.manual_seed(1)
    expected = loss(td.clone())
    torch.manual_seed(1)
    got = loss(td.select(*loss.in_keys))
    for key in loss_terms(expected):
        torch.testing.assert_close(got[key], expected[key], msg=key)
    assert set(expected.keys()) == set(loss.out_keys)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("signal", ["critic", "max"])
def test_collected_keys_are_the_in_keys_a_replay_buffer_stores(variant, signal):
    """``in_keys`` list what the forward reads, the start states and the episodes' cost
    attached to each sample included; ``collected_keys`` is what collected data holds
    (a replay buffer stores ``data.select(*collected_keys(loss))``)."""
    kwargs = {"kappa_signal": signal} if variant[2] == "study" else {}
    loss = make_variant(variant, **kwargs)
    attached = {k for k in loss.in_keys if isinstance(k, tuple) and k[0] == "initial"}
    starts = {(k,) for k in state_keys(loss)} if loss.kappa_states == "initial" else set()
    assert {k[1:] for k in attached} == starts
    assert ("episode_cvar" in loss.in_keys) == (signal == "max" and variant[2] == "study")
    kept = collected_keys(loss)
    assert set(kept) == set(loss.in_keys) - attached - {"episode_cvar"}
    traj = trajectories()
    if loss.cost_n_steps > 1:
        traj = NStepCost.for_loss(loss)(traj)
    traj.reshape(-1).select(*kept)  # (strict: every one is there)
    assert collected_keys(make_sac()) == make_sac().in_keys


# ----------------------------------------------- TestSAC: test_sac_notensordict
@pytest.mark.parametrize("variant", VARIANTS)
def test_keyword_call_equals_the_tensordict_call(variant):
    """``loss(**{flat in_key: tensor})`` (TorchRL's ``dispatch``) gives ``loss(td)``'s
    out_keys, and ``select_out_keys`` narrows it."""
    loss = make_variant(variant)
    td = batch_for(loss)
    kwargs = {_flat_key(k): td.get(k) for k in loss.in_keys}
    torch.manual_seed(0)
    values = loss(**kwargs)
    torch.manual_seed(0)
    out = loss(td)
    assert len(values) == len(loss.out_keys)
    for key, value in zip(loss.out_keys, values, strict=True):
        torch.testing.assert_close(value, out[key], msg=key)
    loss.select_out_keys("loss_actor", "loss_alpha")
    torch.manual_seed(0)
    loss_actor, loss_alpha = loss(**kwargs)
    assert loss_actor == out["loss_actor"] and loss_alpha == out["loss_alpha"]


# ------------------------------------- TestSAC: test_sac_terminating (skip_done_states)
SENTINEL = 1.0e4


def recording_actor():
    """A TorchRL actor that records every observation its network is given."""
    actor, spec = user_actor()
    seen = []
    first = next(m for m in actor.modules() if isinstance(m, nn.Linear))
    first.register_forward_pre_hook(lambda _m, args: seen.append(args[0].detach().clone()))
    return actor, spec, seen


def done_sentinel_batch(loss=None):
    """Next states of done steps hold SENTINEL: an actor must not be asked for them."""
    traj = trajectories()
    done = traj["next", "done"].squeeze(-1)
    traj["next", "observation"][done] = SENTINEL
    return traj if loss is None else prepare(loss, traj)


def assert_actor_never_saw_done_states(seen):
    assert seen, "the actor was never called"
    for obs in seen:
        assert (obs != SENTINEL).all(), "the actor was run on a done next state"


def test_skip_done_states_reference():
    actor, spec, seen = recording_actor()
    loss = SACLoss(actor, user_qvalue(), action_spec=spec, skip_done_states=True)
    out = loss(done_sentinel_batch().reshape(-1))
    assert torch.isfinite(out["loss_actor"])
    assert_actor_never_saw_done_states(seen)


@pytest.mark.parametrize("cls", ["WCSAC", "SACLag"])
@pytest.mark.parametrize("options", ["paper", "study"])
def test_skip_done_states_is_honoured(cls, options):
    """D2: the actor is never run on a done next state (nor, with n-step cost entries,
    on an n-step state after an episode's end), as SACLoss's ``skip_done_states``."""
    actor, spec, seen = recording_actor()
    loss_cls = WCSACLoss if cls == "WCSAC" else SACLagLoss
    kwargs = {"skip_done_states": True, **({"risk_level": 0.5} if cls == "WCSAC" else {})}
    recipe = options_of(options)
    loss = loss_cls(
        actor,
        user_qvalue(),
        user_safety(),
        action_spec=spec,
        **recipe_kwargs(base=recipe, **kwargs),
    )
    batch = done_sentinel_batch(loss)
    seen.clear()
    out = loss(batch)
    assert all(torch.isfinite(out[k]) for k in loss_terms(out))
    total(out).backward()
    assert_actor_never_saw_done_states(seen)
    # without the option the actor does see them (the case above is not vacuous)
    kwargs["skip_done_states"] = False
    actor, spec, seen = recording_actor()
    loss = loss_cls(
        actor,
        user_qvalue(),
        user_safety(),
        action_spec=spec,
        **recipe_kwargs(base=recipe, **kwargs),
    )
    loss(done_sentinel_batch(loss))
    assert any((obs == SENTINEL).any() for obs in seen)


# ------------------------------------------ value estimators (TestMakeValueEstimator)
TD0_FORMS = {
    "enum": lambda: ((ValueEstimators.TD0,), {"gamma": 0.9}),
    "string": lambda: (("td0",), {"gamma": 0.9}),
    "class": lambda: ((TD0Estimator,), {"gamma": 0.9, "value_network": None}),
    "instance": lambda: ((TD0Estimator(gamma=0.9, value_network=None),), {}),
}


@pytest.mark.parametrize("form", sorted(TD0_FORMS))
def test_td0_forms_reference(form):
    loss = make_sac()
    args, kwargs = TD0_FORMS[form]()
    result = loss.make_value_estimator(*args, **kwargs)
    assert result is (loss if form in ("class", "instance") else None)  # (TorchRL's)
    assert isinstance(loss.value_estimator, TD0Estimator)
    assert float(loss.value_estimator.gamma) == pytest.approx(0.9)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("form", sorted(TD0_FORMS))
def test_td0_forms_are_accepted_and_set_gamma(variant, form):
    """D4: every TD(0) form SACLoss takes; γ (and γ_c, the threshold) follow it."""
    loss = make_variant(variant)
    args, kwargs = TD0_FORMS[form]()
    assert loss.make_value_estimator(*args, **kwargs) is loss
    assert isinstance(loss.value_estimator, TD0Estimator)
    assert float(loss.value_estimator.gamma) == pytest.approx(0.9)
    if variant[2] == "paper":  # γ_c follows γ; the per-step threshold is made from it
        assert loss.cost_gamma == pytest.approx(0.9)
        expected = per_step_cost_threshold(loss.cost_limit, 0.9, loss.max_episode_steps)
        assert float(loss.cost_threshold) == pytest.approx(expected, rel=1e-6)
    out = loss(batch_for(loss))
    assert all(torch.isfinite(out[k]) for k in loss_terms(out))


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize(
    "value_type", [ValueEstimators.TD1, ValueEstimators.TDLambda, ValueEstimators.GAE, "gae"]
)
def test_other_value_estimators_are_refused_in_one_line(variant, value_type):
    loss = make_variant(variant)
    with pytest.raises(NotImplementedError) as err:
        loss.make_value_estimator(value_type)
    assert "\n" not in str(err.value) and "TD(0)" in str(err.value)


@pytest.mark.parametrize("variant", VARIANTS)
def test_set_keys_reach_the_value_estimator(variant):
    """TestDefaultForwardValueEstimatorKeys.test_sac_set_keys_forwards_via_default."""
    loss = make_variant(variant)
    loss.make_value_estimator(ValueEstimators.TD0)
    loss.set_keys(value="my_state_value")
    assert loss.value_estimator.tensor_keys.value == "my_state_value"


# ----------------------------------------------------------- compile (test/compile)
@pytest.mark.slow
@pytest.mark.parametrize(
    "variant",
    [
        pytest.param(("WCSAC", "kit", "study"), id="WCSAC-kit-study"),
        pytest.param(("WCSAC", "user", "study"), id="WCSAC-user-study"),
        pytest.param(("SACLag", "kit", "study"), id="SACLag-kit-study"),
        pytest.param(("WCSAC", "kit", "paper"), id="WCSAC-kit-paper"),
    ],
)
def test_forward_compiles_with_fullgraph_and_matches_eager(variant):
    import torch._inductor.config as inductor_config

    loss = make_variant(variant)
    td = batch_for(loss)
    compiled = torch.compile(loss, fullgraph=True)
    with inductor_config.patch(fallback_random=True):
        torch.manual_seed(0)
        got = compiled(td.clone())
        torch.manual_seed(0)
        expected = loss(td.clone())
    assert set(got.keys()) == set(expected.keys())
    for key in expected.keys():
        # inductor fuses and reorders the update (width-8 layers over 24 rows, batch
        # means, the mixture CVaR's float64 search): a few hundred roundings of terms of
        # order 1 + |value|
        assert_close_f32(got[key], expected[key], ops=512, magnitude=1.0 + expected[key].abs())
    total(got).backward()
    assert all(
        p.grad is not None for n, p in loss.named_parameters() if not n.startswith("target_")
    )


# ------------------------------------------------------ TestLossMaskReduction (masking)
MASK_OPTIONS = {
    "paper": {**PAPER_OPTIONS},
    "study": dict(STUDY_OPTIONS),
    "tail-replay": {**PAPER_OPTIONS, "kappa_statistic": "tail"},
    "study-replay": {**STUDY_OPTIONS, "kappa_states": "replay"},
}


def masked_pair(loss_factory):
    """Two batches equal except in their masked-out rows, which hold different garbage
    (finite: a NaN input would make every weight gradient NaN through ``x^T @ 0``)."""
    batches = []
    for garbage_seed in (1, 2):
        loss = loss_factory()
        traj = trajectories()
        mask = torch.ones(BATCH, TIME, dtype=torch.bool)
        mask[:, -2:] = False  # the padded end of each env's piece
        traj.set(("collector", "mask"), mask)
        g = torch.Generator().manual_seed(garbage_seed)
        for key in (
            "observation",
            "action",
            ("next", "observation"),
            ("next", "reward"),
            ("next", "cost"),
        ):
            value = traj.get(key)
            noise = 50.0 * torch.randn(value[~mask].shape, generator=g)
            value[~mask] = noise.clamp(-1, 1) if key == "action" else noise
        batches.append(
            (loss, prepare(loss, traj) if isinstance(loss, WCSACLoss) else traj.reshape(-1))
        )
    return batches


def assert_masked_rows_do_not_count(batches):
    results = []
    for loss, td in batches:
        torch.manual_seed(0)
        out = loss(td)
        total(out).backward()
        grads = {n: p.grad.clone() for n, p in loss.named_parameters() if p.grad is not None}
        results.append((out, grads))
    (out_a, grad_a), (out_b, grad_b) = results
    for key in loss_terms(out_a):
        torch.testing.assert_close(out_a[key], out_b[key], msg=key)
    assert grad_a.keys() == grad_b.keys()
    for name in grad_a:
        torch.testing.assert_close(grad_a[name], grad_b[name], msg=name)


def test_masking_reference():
    assert_masked_rows_do_not_count(masked_pair(lambda: make_sac()))


@pytest.mark.parametrize("risk_level", [0.05, 0.5, 1.0])
def test_a_weighted_mixture_is_the_mixture_of_the_rows_kept(risk_level):
    """The mixtures κ reads with ``kappa_statistic="tail"``: rows of weight 0 (masked)
    count for nothing, whatever they hold (NaN, inf), and send no gradient; weights all
    one give the equal-weight mixture."""
    g = torch.Generator().manual_seed(0)
    keep = torch.tensor([True, False, True, True, False, True, True, False])
    mean = torch.randn(8, generator=g, dtype=torch.float64).requires_grad_()
    variance = torch.rand(8, generator=g, dtype=torch.float64) + 0.1
    garbage = torch.tensor([0.0, float("nan"), 0.0, 0.0, float("inf"), 0.0, 0.0, -1e30])
    bad_mean = torch.where(keep, mean, garbage.double())
    got = gaussian_mixture_cvar(bad_mean, variance, risk_level, weights=keep)
    expected = gaussian_mixture_cvar(mean[keep], variance[keep], risk_level)
    # (both brackets shrink 32^5-fold from the kept rows' own VaRs: the same search)
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)
    got.backward()
    assert torch.isfinite(mean.grad).all() and (mean.grad[~keep] == 0).all()
    everyone = torch.ones(8, dtype=torch.bool)
    torch.testing.assert_close(
        gaussian_mixture_cvar(mean, variance, risk_level, weights=everyone),
        gaussian_mixture_cvar(mean, variance, risk_level),
        rtol=1e-12,
        atol=1e-12,
    )
    quantiles = torch.randn(8, 5, generator=g)
    bad = torch.where(keep.unsqueeze(-1), quantiles, garbage.unsqueeze(-1))
    got = quantile_mixture_cvar(bad, risk_level, weights=keep)
    expected = quantile_mixture_cvar(quantiles[keep], risk_level)
    assert_close_f32(got, expected, ops=40, magnitude=quantiles.abs().max())
    assert_close_f32(
        quantile_mixture_cvar(quantiles, risk_level, weights=everyone),
        quantile_mixture_cvar(quantiles, risk_level),
        ops=40,
        magnitude=quantiles.abs().max(),
    )


# D7: masked rows stay out of the κ statistic too (kappa_statistic="tail" mixes the rows)
MASK_CASES = [
    pytest.param(cls, critic, options, id=f"{cls}-{critic}-{options}")
    for cls in ("WCSAC", "SACLag")
    for critic in ("kit", "user")
    for options in MASK_OPTIONS
]


@pytest.mark.parametrize("cls,critic,options", MASK_CASES)
def test_masked_rows_do_not_count(cls, critic, options):
    def factory():
        loss = make_variant((cls, critic, "paper"), **{**MASK_OPTIONS[options]})
        return loss

    assert_masked_rows_do_not_count(masked_pair(factory))


# ------------------------------------------- test_loss_exploration (deterministic sampling)
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize(
    "mode", [ExplorationType.DETERMINISTIC, ExplorationType.MEAN, ExplorationType.MODE]
)
def test_the_loss_samples_whatever_the_exploration_type(variant, mode):
    """SAC's losses draw reparametrised actions: a deterministic exploration type set
    around the call changes nothing, and is restored after it."""
    loss = make_variant(variant)
    td = batch_for(loss)
    torch.manual_seed(0)
    with set_exploration_type(ExplorationType.RANDOM):
        expected = loss(td.clone())
    torch.manual_seed(0)
    with set_exploration_type(mode):
        got = loss(td.clone())
        assert exploration_type() == mode
    for key in loss_terms(expected):
        torch.testing.assert_close(got[key], expected[key], msg=key)
    torch.manual_seed(1)
    other = loss(td.clone())
    assert not torch.equal(other["loss_actor"], expected["loss_actor"])  # it does sample


# ----------------------------------------------------- TestBuffer.test_module_cast
@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("dest", [torch.float64, torch.device("cpu")], ids=["float64", "cpu"])
def test_module_cast_moves_every_tensor_and_keeps_the_parameters(variant, dest):
    loss = make_variant(variant)
    params_before = set(loss.parameters())
    leaves_before = {
        name: set(getattr(loss, f"{name}_network_params").values(True, True))
        for name in ("actor", "qvalue", "safety")
    }
    loss.to(dest)
    assert set(loss.parameters()) == params_before  # an optimizer built before still works
    for name, leaves in leaves_before.items():
        assert set(getattr(loss, f"{name}_network_params").values(True, True)) == leaves
    for name, p in loss.named_parameters():
        assert isinstance(p, nn.Parameter), name
    tensors = [*loss.named_parameters(), *loss.named_buffers()]
    for prefix in ("target_qvalue_network_params", "target_safety_network_params"):
        tensors += [(f"{prefix}.{k}", v) for k, v in getattr(loss, prefix).items(True, True)]
    for name, tensor in tensors:
        if isinstance(dest, torch.dtype):
            if tensor.is_floating_point():
                assert tensor.dtype == dest, name
        else:
            assert tensor.device.type == dest.type, name


@pytest.mark.parametrize("variant", VARIANTS)
def test_meta_device_as_sacloss(variant):
    """TorchRL 0.14.1's SACLoss can neither move to nor be built on the meta device
    (TensorDictParams' ``set_data``; ``.item()`` in its constructor): the safe losses,
    built on it, fail the same way, in their ``SACLoss`` part, and lose nothing."""
    for build in (make_sac, lambda: make_variant(variant)):
        loss = build()
        before = {k: v.clone() for k, v in loss.state_dict().items()}
        with pytest.raises(RuntimeError, match="incompatible tensor type"):
            loss.to("meta")
        with pytest.raises(RuntimeError, match="meta tensors"):
            with torch.device("meta"):
                build()
        assert {k: v.device.type for k, v in loss.state_dict().items()} == {
            k: "cpu" for k in before
        }


@pytest.mark.parametrize("variant", VARIANTS)
def test_a_float64_loss_runs_on_a_float64_batch(variant):
    loss = make_variant(variant).to(torch.float64)
    td = batch_for(loss).apply(lambda t: t.double() if t.is_floating_point() else t)
    out = loss(td)
    for key in loss_terms(out):
        assert out[key].dtype == torch.float64 and torch.isfinite(out[key]), key
    total(out).backward()


# ---------------------------------------------- TestSAC: target entropy, reduction
@pytest.mark.parametrize("variant", VARIANTS)
def test_target_entropy_auto_is_minus_the_action_dim(variant):
    assert make_variant(variant).target_entropy.item() == -ACT
    assert make_variant(variant, target_entropy=-2.5).target_entropy.item() == -2.5


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("reduction", [None, "none", "mean", "sum"])
def test_reduction(variant, reduction):
    kwargs = {"reduction": reduction} if reduction else {}
    if reduction == "none":
        kwargs["scalar_output_mode"] = "exclude"
    loss = make_variant(variant, **kwargs)
    td = batch_for(loss)
    out = loss(td)
    for key in loss_terms(out):
        assert out[key].shape == (td.shape if reduction == "none" else torch.Size([])), key
    if reduction in ("mean", "sum"):  # each term reduced from the per-row ones
        rows = make_variant(variant, reduction="none", scalar_output_mode="exclude")
        torch.manual_seed(0)
        per_row = rows(td.clone())
        loss = make_variant(variant, **kwargs)
        torch.manual_seed(0)
        reduced = loss(td.clone())
        for key in loss_terms(reduced):
            value = getattr(per_row[key], reduction)()
            assert_close_f32(
                reduced[key], value, ops=64, magnitude=per_row[key].abs().max(), msg=key
            )


# ---------------------------------------- TestSAC: test_sac_prioritized_weights
@pytest.mark.parametrize("variant", VARIANTS)
def test_prioritized_replay_weights(variant):
    """With ``priority_weight`` in the batch (a prioritized buffer's importance weights)
    every loss term is the weighted mean of its per-row terms; ``td_error`` is written."""
    loss = make_variant(variant)
    td = batch_for(loss)
    weights = torch.rand(td.shape, generator=torch.Generator().manual_seed(4)) + 0.5
    td.set("priority_weight", weights)
    torch.manual_seed(0)
    weighted = loss(td.clone())
    rows = make_variant(variant, reduction="none", scalar_output_mode="exclude")
    rows.load_state_dict(loss.state_dict())
    plain = td.clone().exclude("priority_weight")
    torch.manual_seed(0)
    per_row = rows(plain)
    assert loss.tensor_keys.priority in plain.keys()
    for key in loss_terms(weighted):
        expected = (per_row[key] * weights).sum() / weights.sum()  # TorchRL's weighted mean
        magnitude = (per_row[key] * weights).abs().max()
        assert_close_f32(weighted[key], expected, ops=64, magnitude=magnitude, msg=key)
    unweighted = make_variant(variant, use_prioritized_weights=False)
    unweighted.load_state_dict(loss.state_dict())
    torch.manual_seed(0)
    assert_close_f32(
        unweighted(td.clone())["loss_qvalue"],
        per_row["loss_qvalue"].mean(),
        ops=64,
        magnitude=per_row["loss_qvalue"].abs().max(),
    )


# ------------------------------------------- TestSAC: test_sac_deactivate_vmap
@pytest.mark.parametrize("variant", VARIANTS)
def test_deactivate_vmap_gives_the_same_losses(variant):
    outs = []
    for deactivate in (False, True):
        loss = make_variant(variant, deactivate_vmap=deactivate)
        td = batch_for(loss)
        torch.manual_seed(0)
        outs.append(loss(td))
    for key in loss_terms(outs[0]):
        assert_close_f32(outs[1][key], outs[0][key], ops=32, msg=key)


# -------------------------------------- D8: a composite actor and the kit's transforms
@pytest.mark.parametrize("cls", ["WCSAC", "SACLag"])
def test_a_composite_actor_runs_through_the_kit_transforms(cls):
    actor, spec = user_actor(composite=True)
    loss_cls = WCSACLoss if cls == "WCSAC" else SACLagLoss
    kwargs = {"risk_level": 0.5} if cls == "WCSAC" else {}
    loss = loss_cls(actor, user_qvalue(), user_safety(), action_spec=spec, **kwargs)
    assert state_keys(loss) == ["observation"]  # not the actor's own "params"
    traj = trajectories(composite=True)
    traj = NStepCost.for_loss(loss)(traj)
    assert set(traj["nstep"].keys()) == {"observation", "cost", "steps", "terminated", "done"}
    starts = StartStateBuffer.for_loss(loss)
    assert starts.add_starts(traj) == BATCH * TIME // 3
    episodes = EpisodeCostWindow.for_loss(loss)  # (the kit's recipe: κ reads episodes too)
    out = loss(episodes.attach(starts.attach(traj.reshape(-1))))
    total(out).backward()
    for name, p in loss.named_parameters():
        assert name.startswith("target_") or (p.grad is not None and p.grad.norm() > 0), name


# ------------------------------------------------------- the first call: a plain batch
def plain_batch(terminated=False):
    """What a TorchRL replay buffer hands over: observation, action, next reward / done
    / cost (and no more)."""
    traj = trajectories()
    keys = ["observation", "action", ("next", "observation"), ("next", "reward")]
    keys += [("next", "done"), ("next", "cost")] + ([("next", "terminated")] if terminated else [])
    return traj.select(*keys).reshape(-1)


@pytest.mark.parametrize("variant", VARIANTS)
def test_missing_inputs_names_the_transforms_in_one_line(variant):
    loss = make_variant(variant)
    message = missing_inputs(loss, plain_batch(terminated=True))
    if variant[2] == "paper":
        assert message is None
        return
    assert "\n" not in message
    for name in ("NStepCost.for_loss(loss)", "StartStateBuffer.for_loss(loss)", "PAPER_OPTIONS"):
        assert name in message, name
    assert missing_inputs(loss, batch_for(loss)) is None
    signal = make_variant(variant, kappa_signal="max")
    assert missing_inputs(signal, batch_for(signal)) is None
    without = batch_for(signal).exclude("episode_cvar")
    assert "EpisodeCostWindow.for_loss(loss)" in missing_inputs(signal, without)


@pytest.mark.parametrize("variant", VARIANTS)
def test_a_plain_batch_trains_or_names_the_missing_transforms(variant):
    """The first call a TorchRL user makes, on what a replay buffer hands over: under
    PAPER_OPTIONS it trains; under the defaults a ``KeyError`` names in one line every
    transform to add (not the first missing entry only) and PAPER_OPTIONS."""
    loss = make_variant(variant)
    batch = plain_batch(terminated=True)
    before = {k: v.clone() for k, v in loss.state_dict().items()}
    if variant[2] == "paper":
        out = loss(batch)
        assert all(torch.isfinite(out[k]) for k in loss_terms(out))
        total(out).backward()
        return
    with check_td_steady(batch), pytest.raises(KeyError) as err:
        loss(batch)
    message = err.value.args[0]
    assert "\n" not in message
    for name in ("NStepCost.for_loss(loss)", "StartStateBuffer.for_loss(loss)", "PAPER_OPTIONS"):
        assert name in message, name
    for key, value in loss.state_dict().items():  # nothing lost
        torch.testing.assert_close(value, before[key], msg=key)


@pytest.mark.parametrize("variant", VARIANTS)
def test_a_batch_without_terminated_falls_back_to_done(variant):
    """D9: SACLoss trains on a batch whose only end flag is ``done`` (TorchRL's TD(0)
    reads ``done`` where ``terminated`` is absent); so must the safety critic's target,
    one-step or through NStepCost."""
    sac = make_sac()
    assert torch.isfinite(sac(plain_batch())["loss_qvalue"])
    loss = make_variant(variant)

    def batch(with_flag: bool):
        traj = trajectories().exclude(("next", "terminated"))
        if with_flag:
            traj["next", "terminated"] = traj["next", "done"].clone()
        return prepare(loss, traj)

    torch.manual_seed(0)
    without = loss(batch(False))
    torch.manual_seed(0)
    with_flag = loss(batch(True))
    for key in loss_terms(with_flag):
        torch.testing.assert_close(without[key], with_flag[key], msg=key)


# ------------------------------------------------------------- the optimizer trap
@pytest.mark.parametrize("variant", VARIANTS)
def test_param_groups_hold_every_trainable_parameter_once_at_the_kit_rates(variant):
    loss = make_variant(variant)
    groups = param_groups(loss, 1e-3, actor_lr=3e-4, kappa_lr_scale=5.0)
    assert [g["name"] for g in groups] == ["actor", "critic", "alpha", "kappa"]
    assert [g["lr"] for g in groups] == [3e-4, 1e-3, 1e-3, 5e-3]
    listed = [p for g in groups for p in g["params"]]
    assert len({id(p) for p in listed}) == len(listed)
    trainable = {id(p) for p in loss.parameters() if p.requires_grad}
    assert {id(p) for p in listed} == trainable
    assert groups[3]["params"] == [loss.kappa_raw]
    with pytest.raises(ValueError, match="lr must be a number > 0"):
        param_groups(loss, 0.0)


def test_param_groups_of_a_plain_sacloss():
    loss = make_sac()
    groups = param_groups(loss, 1e-3)
    assert [g["name"] for g in groups] == ["actor", "critic", "alpha"]


def _step(optim, loss):
    out = loss(batch_for(loss))
    total(out).backward()
    optim.step()
    optim.zero_grad()


@pytest.mark.parametrize("variant", VARIANTS)
def test_one_group_over_all_parameters_warns_once_in_one_line(variant):
    loss = make_variant(variant)
    optim = torch.optim.Adam(loss.parameters(), lr=1e-3)  # the TorchRL way
    with pytest.warns(SingleGroupWarning) as caught:
        _step(optim, loss)
    messages = [str(w.message) for w in caught if w.category is SingleGroupWarning]
    assert len(messages) == 1 and "\n" not in messages[0]
    assert "param_groups(loss" in messages[0] and "kappa_raw" in messages[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error", SingleGroupWarning)
        _step(optim, loss)  # once per optimizer
    # a deep copy (e.g. a checkpointed loss) is watched too
    copy = deepcopy(loss)
    with pytest.warns(SingleGroupWarning):
        _step(torch.optim.Adam(copy.parameters(), lr=1e-3), copy)


@pytest.mark.parametrize("variant", VARIANTS)
def test_the_kit_groups_do_not_warn(variant):
    loss = make_variant(variant)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SingleGroupWarning)
        _step(torch.optim.Adam(param_groups(loss, 1e-3, kappa_lr_scale=5.0)), loss)
        separate = [torch.optim.Adam([g]) for g in param_groups(loss, 1e-3)]
        out = loss(batch_for(loss))
        total(out).backward()
        for optim in separate:
            optim.step()
        # κ alone at the same rate as the rest is a choice, not the trap
        sac = make_sac()
        optim = torch.optim.Adam(sac.parameters(), lr=1e-3)
        total(sac(trajectories().reshape(-1))).backward()
        optim.step()


# ------------------------------------------ docs/torchrl_contract.md: the example's diff
def test_the_doc_diff_is_the_example():
    """The diff docs/torchrl_contract.md shows (the SACLoss loop -> examples/pendulum_wcsac.py):
    each hunk's new side is a run of the example's lines, and no removed line is in it."""
    root = Path(__file__).resolve().parents[1]
    doc = (root / "docs" / "torchrl_contract.md").read_text()
    block = doc.split("```diff\n", 1)[1].split("```", 1)[0].splitlines()
    example = (root / "examples" / "pendulum_wcsac.py").read_text().splitlines()
    assert block[0].startswith("--- ") and block[1] == "+++ examples/pendulum_wcsac.py"
    hunks, removed = [], []
    for line in block[2:]:
        if line.startswith("@@"):
            hunks.append([])
        elif line.startswith("-"):
            removed.append(line[1:])
        else:  # (a blank context line may have lost its space)
            assert line[:1] in ("", " ", "+"), line
            hunks[-1].append(line[1:])
    assert len(hunks) >= 3 and removed
    for hunk in hunks:
        n = len(hunk)
        assert any(example[i : i + n] == hunk for i in range(len(example) - n + 1)), hunk[:3]
    for line in removed:
        assert line.strip() == "" or line not in example, line
