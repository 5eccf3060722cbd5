"""Off-policy learning for WCSAC, SAC-Lag and SAC: replay buffer, UTD updates, polyak targets.

The trainer of every off-policy entry of :data:`~wcsac_rl.training.registry.ALGORITHMS`
(the loss from :func:`~wcsac_rl.training.registry.make_loss`). After each collector
batch, the entries the loss reads go into the replay buffer and ``frames_per_batch ×
utd_ratio`` gradient steps follow, once ``init_random_frames`` random frames have been
collected. The collected batches get the n-step cost entries (``algo.cost_n_steps``,
:class:`~wcsac_rl.training.replay.NStepReplayBuffer`), and the sampled ones the start
states (``algo.kappa_states=initial``) and the recent episodes' CVaR
(``algo.kappa_signal``) the loss reads: docs/loss.md, "The loss, term by term". Off the
CPU the collector acts with a CPU copy of the actor (:mod:`~wcsac_rl.training.devices`).
"""

from __future__ import annotations

import copy
import math
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl import timeit

from wcsac_rl.modules.actor import TanhNormalPolicy
from wcsac_rl.objectives.inputs import collected_keys
from wcsac_rl.rollouts.critic_calibration import supports_calibration
from wcsac_rl.training import builders, registry
from wcsac_rl.training.checkpoint import (
    CHECKPOINT_DIR,
    INITIAL_STATE_BUFFER_DIR,
    REPLAY_BUFFER_DIR,
    load_buffers,
    load_module_state,
    load_optimizer_state,
    remove_unreferenced_buffers,
    save_buffers,
    verify_buffers,
)
from wcsac_rl.training.devices import run_devices
from wcsac_rl.training.preemption import DeferredSignals
from wcsac_rl.training.replay import draw_indices, nested_key, sample_at
from wcsac_rl.training.trainer import Trainer, env_max_episode_steps
from wcsac_rl.training.training_calibration import TrainingCalibration

__all__ = ["OffPolicyTrainer"]


class OffPolicyTrainer(Trainer):
    """:class:`~wcsac_rl.training.trainer.Trainer` with a replay buffer and gradient updates."""

    def _build_learner(self) -> None:
        cfg = self.cfg
        collector_cfg = cfg.algo.collector
        self.agent = builders.make_agent(cfg, self.env)
        self.loss = registry.make_loss(cfg, self.agent, self.max_episode_steps)
        self.target_updater = builders.make_target_updater(cfg, self.loss)
        self.optimizers = builders.make_optimizers(cfg, self.loss)
        # n-step cost entries (cost_n_steps > 1), added to each collected batch
        self.postproc = builders.make_postproc(self.loss)
        # what a replay batch holds: what the loss reads but is not attached to each
        # sample (smaller buffer, faster sampling); stored: all of it but the n-step
        # state, which the buffer reads from the row that holds it
        self.replay_keys = sorted(collected_keys(self.loss), key=str)
        self.replay_buffer = builders.make_replay_buffer(cfg, self.postproc, self.replay_keys)
        gathered = set(getattr(self.replay_buffer, "gathered_keys", ()))
        self.stored_keys = [key for key in self.replay_keys if nested_key(key) not in gathered]
        self.initial_state_buffer = None
        if getattr(self.loss, "kappa_states", "replay") == "initial":
            self.initial_state_buffer = builders.make_initial_state_buffer(cfg, self.loss)
        # algo.kappa_hold_goal_rate: κ's optimizer waits for the task to be learned
        self.kappa_hold_goal_rate = float(cfg.algo.get("kappa_hold_goal_rate", 0.0))
        self.kappa_held = self.kappa_hold_goal_rate > 0  # (its rules: validate_config)
        self.episode_window = None
        head = getattr(self.loss, "safety_head", None)
        if getattr(self.loss, "kappa_signal", "critic") != "critic" or (
            getattr(head, "reads_episode_costs", False)  # (an adaptive k_ucb)
        ):
            self.episode_window = builders.make_episode_window(cfg, self.loss)
        self.updates_per_batch = max(
            1, round(int(collector_cfg.frames_per_batch) * float(collector_cfg.utd_ratio))
        )
        self.init_random_frames = int(collector_cfg.init_random_frames)
        # frames after which gradient steps start (moved on resume, see load_learner_state)
        self.update_start_frames = self.init_random_frames
        # collection and test episodes act through the fast path of make_actor actors
        self.policy = TanhNormalPolicy(self.agent.actor)
        # algo.shield: the collector acts through a CriticShield (test episodes do not)
        collection = builders.make_collection_policy(cfg, self.loss, self.policy)
        self.collection_policy = None if collection is self.policy else collection
        # a learner off the CPU: the collector acts with a CPU copy of the actor (devices.py)
        self.acting_copy: TanhNormalPolicy | None = None
        copy_on_cpu = self.collect_on_cpu_copy
        if copy_on_cpu is None:  # (meta, for device tests, holds nothing to copy)
            copy_on_cpu = run_devices(cfg).learner.type not in ("cpu", "meta")
        if copy_on_cpu and self.collection_policy is None:
            self.acting_copy = TanhNormalPolicy(copy.deepcopy(self.agent.actor).to("cpu"))
            self._acting_weights = TensorDict.from_module(self.acting_copy.actor).data
            self._learner_weights = TensorDict.from_module(self.agent.actor).data
        self.shield_steps = self.shield_replaced = 0  # of the epoch in progress
        # the safety critic's reading of each collected batch against what its episodes
        # then cost (train_calib/* columns; SAC has no safety critic)
        self.training_calibration = (
            TrainingCalibration(self.loss, cost_limit=float(cfg.cost_limit))
            if supports_calibration(self.loss)
            else None
        )
        # the updates of the batch in progress, read together after it (learn)
        self._pending: list[tuple[TensorDictBase, torch.Tensor]] | None = None
        # fused Adam skips a step on the device (found_inf); other optimizers are read
        self._masked_steps = all(o.defaults.get("fused") for o in self.optimizers.values())
        # compile=true: the whole update is one compiled function; cudagraphs=true: it is
        # captured as a CUDA graph per set of stepped optimizers (docs/performance.md)
        self._update_step = torch.compile(self._device_step) if cfg.compile else self._device_step
        self._graphs: dict[bool, Any] | None = {} if cfg.get("cudagraphs", False) else None
        self._graph_warmup = 5 if cfg.compile else 2  # (eager updates before the capture)
        # replay_draw=round: the rows of all a batch's updates drawn in one call, on the
        # learner (another random stream than one draw per update)
        self.replay_draw = str(cfg.get("replay_draw", "update"))

    collect_on_cpu_copy: bool | None = None
    """Whether the collector acts with a CPU copy of the actor; ``None``: where the
    learner is not the CPU (``True`` on a CPU learner: the copy, for tests)."""

    def collector_policy(self):
        return self.acting_copy if self.acting_copy is not None else super().collector_policy()

    def refresh_acting_copy(self) -> None:
        """The collector's CPU copy of the actor takes the learner's weights (one copy
        from the device; nothing without a copy)."""
        if self.acting_copy is not None:
            self._acting_weights.update_(self._learner_weights)

    @property
    def loss_keys(self) -> list[str]:
        return list(self.loss.out_keys)

    def sample(self, index: torch.Tensor | None = None) -> TensorDictBase:
        """A replay batch (with a start state per row when the loss needs them): drawn
        by the replay buffer, or its rows at ``index`` (``replay_draw=round``)."""
        if index is None:
            batch = self.replay_buffer.sample()
        else:
            batch = sample_at(self.replay_buffer, index)
        if self.initial_state_buffer is not None:
            batch = self.initial_state_buffer.attach(batch)
        if self.episode_window is not None:
            batch = self.episode_window.attach(batch)
        return batch

    def update(self, batch: TensorDictBase) -> TensorDictBase | None:
        """One gradient step on every parameter group (one backward of the terms' sum: each term
        reaches only its own parameters), then the polyak update of the targets.

        A non-finite loss or gradient is never stepped on: the step is masked on the device
        (fused Adam's ``found_inf``, a Polyak weight of 0; docs/performance.md) and counted as
        skipped (:meth:`skip_update`). Called by itself, the update reads whether it was
        skipped and returns ``None`` if so; in :meth:`learn` a batch's updates are read together.
        """
        out, finite = self._step(batch)
        self.updates += 1  # (a skipped update is taken back when it is read)
        if self._pending is not None:
            self._pending.append((out, finite))
            return out
        return self._count([(out, finite)])[0]

    def _step(self, batch: TensorDictBase) -> tuple[TensorDictBase, torch.Tensor]:
        """The update of :meth:`update`, masked on the device where it is not finite: the
        loss outputs and that flag (a boolean tensor), nothing read back; compiled with
        ``compile=true``, replayed as a CUDA graph with ``cudagraphs=true``."""
        if self._graphs is None:
            return self._update_step(batch)
        graph = self._graphs.get(self.kappa_held)
        if graph is None:
            from tensordict.nn import CudaGraphModule

            graph = self._graphs[self.kappa_held] = CudaGraphModule(
                self._graph_step, in_keys=[], out_keys=[], warmup=self._graph_warmup
            )
        result = graph(batch)
        return result["out"], result["finite"]

    def _graph_step(self, batch: TensorDictBase) -> TensorDictBase:
        """:meth:`_device_step` with its results in one tensordict (``CudaGraphModule``)."""
        out, finite = self._update_step(batch)
        return TensorDict({"out": out, "finite": finite}, batch_size=[])

    def _device_step(self, batch: TensorDictBase) -> tuple[TensorDictBase, torch.Tensor]:
        out = self.loss(batch)
        total = sum(value for key, value in out.items() if key.startswith("loss_"))
        total.backward()
        grad_norm = torch.nn.utils.get_total_norm(self._grads())
        finite = torch.isfinite(total) & torch.isfinite(grad_norm)
        stepped = [
            optimizer
            for name, optimizer in self.optimizers.items()
            if not (name == "kappa" and self.kappa_held)  # (held: not stepped at all)
        ]
        if self._masked_steps:
            skip = (~finite).to(torch.float32)
            for optimizer in stepped:
                optimizer.found_inf = skip  # (fused Adam: no step where it is 1)
        elif not bool(finite):  # an optimizer without a masked step: read it here
            stepped = []
        for optimizer in stepped:
            optimizer.step()
            optimizer.found_inf = None  # (a later step of its own is not masked)
        for optimizer in self.optimizers.values():
            optimizer.zero_grad(set_to_none=True)
        self.target_updater.step(finite)
        return out.detach(), finite

    def _count(
        self, steps: list[tuple[TensorDictBase, torch.Tensor]]
    ) -> list[TensorDictBase | None]:
        """Read which of ``steps`` were finite (one host read for all), take the others
        back from :attr:`updates` and count them as skipped: their outputs, ``None``
        for a skipped one."""
        if not steps:
            return []
        flags = torch.stack([finite for _, finite in steps]).tolist()
        outputs: list[TensorDictBase | None] = []
        for (out, _), finite in zip(steps, flags):
            if finite:
                self.nonfinite_streak = 0
                outputs.append(out)
                continue
            self.updates -= 1
            bad = [k for k, v in out.items() if k.startswith("loss_") and not v.isfinite().all()]
            self.skip_update(f"loss ({', '.join(bad)})" if bad else "gradient")
            outputs.append(None)
        return outputs

    def _grads(self) -> list[torch.Tensor]:
        return [
            p.grad
            for optimizer in self.optimizers.values()
            for group in optimizer.param_groups
            for p in group["params"]
            if p.grad is not None
        ]

    def learn(self, batch: TensorDictBase) -> list[TensorDictBase]:
        if self.training_calibration is not None:
            with timeit("train_calib"):  # read before the updates that learn from it
                self.training_calibration.add(batch)
        with timeit("replay_extend"):
            if self.postproc is not None:
                batch = self.postproc(batch)
            self.replay_buffer.extend(batch.reshape(-1).select(*self.stored_keys))
            if self.initial_state_buffer is not None:
                self.initial_state_buffer.add_starts(batch)
            if self.episode_window is not None:
                self.episode_window.add_episodes(batch)
            # (the warm-up's random batches hold the flag too, all False: not counted;
            # the collector rounds the warm-up up to whole batches)
            start = self.tracker.frames - batch.numel()
            warm_up = -(-self.init_random_frames // batch.numel()) * batch.numel()
            if self.collection_policy is not None and start >= warm_up:
                self.shield_steps += batch.numel()
                self.shield_replaced += int(batch.get("shielded").sum())
        if self.tracker.frames < self.update_start_frames:
            return []
        self._pending = []
        try:
            # Ctrl-C lands between updates, never inside one: a KeyboardInterrupt inside
            # TorchRL's vmapped critics surfaces as another error (no checkpoint, no
            # resume command), and one inside an optimizer step would checkpoint a
            # half-stepped network. Held back, it ends the loop after its update.
            with timeit("update"), DeferredSignals(("SIGINT",)) as ctrl_c:
                indices = None  # (replay_draw=round: the batch's rows drawn at once)
                if self.replay_draw == "round":
                    indices = draw_indices(self.replay_buffer, self.updates_per_batch)
                for i in range(self.updates_per_batch):
                    self.update(self.sample() if indices is None else self.sample(indices[i]))
                    if ctrl_c.received is not None:
                        break
        finally:  # (also when interrupted: the counters are the steps taken)
            steps, self._pending = self._pending, None
            outputs = self._count(steps)
            self.refresh_acting_copy()
        return [out for out in outputs if out is not None]

    def observe_training_episodes(self, metrics: dict[str, float]) -> None:
        """With ``algo.kappa_hold_goal_rate``: release κ after the first epoch whose
        ``train/goal_rate`` reached it (for good: a later slower epoch does not hold it
        again)."""
        rate = metrics.get("train/goal_rate", math.nan)
        if self.kappa_held and rate >= self.kappa_hold_goal_rate:  # (NaN: no episode ended)
            self.kappa_held = False

    def collection_metrics(self) -> dict[str, float]:
        """With a safety critic, its reading of the epoch's training episodes against
        their realised cost-to-go (``train_calib/*``,
        :mod:`~wcsac_rl.training.training_calibration`); with a shield,
        ``train/shielded``, the fraction of the epoch's policy steps (the random warm-up
        has none) whose action the shield replaced."""
        metrics = {}
        if self.training_calibration is not None:
            metrics.update(self.training_calibration.epoch_metrics())
        if self.collection_policy is not None:
            steps, replaced = self.shield_steps, self.shield_replaced
            self.shield_steps = self.shield_replaced = 0
            metrics["train/shielded"] = replaced / steps if steps else 0.0
        if self.kappa_hold_goal_rate > 0:  # 1: still held after this epoch (0: released)
            metrics["train/kappa_held"] = float(self.kappa_held)
        return metrics

    def observe_test_episodes(self, results: list) -> None:
        if self.episode_window is not None and self.episode_window.test_window:
            self.episode_window.add_test_costs(result.cost for result in results)

    @classmethod
    def restore_policy(cls, cfg, learner_state, env):
        agent = builders.make_agent(cfg, env)
        max_steps = env_max_episode_steps(cfg)
        loss = registry.make_loss(cfg, agent, max_steps)
        load_module_state(loss, learner_state.get("loss"))  # the actor shares these parameters
        return TanhNormalPolicy(agent.actor)

    # ---------------------------------------------------------- checkpoint
    # save_replay_buffer=true: checkpoints/buffers-<frames>/ (docs/training.md)
    _saved_buffers: dict[str, Any] | None = None

    def learner_state(self) -> dict[str, Any]:
        state = {
            "loss": self.loss.state_dict(),
            "optimizers": {k: opt.state_dict() for k, opt in self.optimizers.items()},
        }
        if self.episode_window is not None:
            state["episode_window"] = self.episode_window.state_dict()
        if self.collection_policy is not None:  # (the epoch in progress: a mid-epoch save)
            state["shield"] = {"steps": self.shield_steps, "replaced": self.shield_replaced}
        if self.training_calibration is not None:  # (the epoch in progress, too)
            state["training_calibration"] = self.training_calibration.state_dict()
        if self.kappa_hold_goal_rate > 0:
            state["kappa_held"] = self.kappa_held
        if self.cfg.save_replay_buffer and len(self.replay_buffer):
            state["buffers"] = self._save_buffers()
        return state

    def _save_buffers(self) -> dict[str, Any]:
        frames = self.tracker.frames
        saved = self._saved_buffers
        if saved is not None and saved["frames"] == frames:
            return saved  # nothing was added since the last save (e.g. the final one)
        buffers = {REPLAY_BUFFER_DIR: self.replay_buffer}
        if self.initial_state_buffer is not None and len(self.initial_state_buffer):
            buffers[INITIAL_STATE_BUFFER_DIR] = self.initial_state_buffer
        manifest = save_buffers(self.run_dir / CHECKPOINT_DIR, buffers, frames=frames)
        self._saved_buffers = {**manifest, "frames": frames}
        return self._saved_buffers

    def after_save(self, state: dict[str, Any]) -> None:
        # the new checkpoint is in place: older checkpoints' buffers can go
        keep = (state["learner"].get("buffers") or {}).get("dir")
        remove_unreferenced_buffers(self.run_dir / CHECKPOINT_DIR, keep)

    def _buffers_to_load(self, state: dict[str, Any]):
        """The directory holding the checkpoint's saved buffers (verified), or ``None``."""
        checkpoint_dir = self.run_dir / CHECKPOINT_DIR
        manifest = state.get("buffers")
        if manifest:
            directory = verify_buffers(checkpoint_dir, manifest, self.checkpoint_path)
            if directory is None:
                print(
                    f"{self.run_dir}: the replay buffer saved with the checkpoint is gone "
                    f"({checkpoint_dir / manifest['dir']}); it is refilled instead"
                )
            else:
                self._saved_buffers = {**manifest, "frames": self.tracker.frames}
            return directory
        if (checkpoint_dir / REPLAY_BUFFER_DIR).is_dir():  # saved before manifests (unchecked)
            return checkpoint_dir
        return None

    def load_learner_state(self, state: dict[str, Any]) -> None:
        load_module_state(self.loss, state.get("loss"))
        self.refresh_acting_copy()
        for key, optimizer in self.optimizers.items():
            load_optimizer_state(optimizer, state["optimizers"][key])
        if self.episode_window is not None and "episode_window" in state:
            self.episode_window.load_state_dict(state["episode_window"])
        if self.collection_policy is not None and "shield" in state:
            self.shield_steps = int(state["shield"]["steps"])
            self.shield_replaced = int(state["shield"]["replaced"])
        if self.training_calibration is not None and "training_calibration" in state:
            self.training_calibration.load_state_dict(state["training_calibration"])
        if self.kappa_hold_goal_rate > 0:
            self.kappa_held = bool(state.get("kappa_held", self.kappa_held))
        directory = self._buffers_to_load(state)
        if directory is not None:
            buffers = {REPLAY_BUFFER_DIR: self.replay_buffer}
            if self.initial_state_buffer is not None:
                buffers[INITIAL_STATE_BUFFER_DIR] = self.initial_state_buffer
            # saved with a manifest: delete its whole buffers-<frames>/ to refill instead
            manifest = directory != self.run_dir / CHECKPOINT_DIR
            load_buffers(
                buffers, directory, self.checkpoint_path, remove=directory if manifest else None
            )
            # exact resume: the warm-up threshold stays where an uninterrupted run has it
            self.update_start_frames = self.init_random_frames
        else:
            # No saved buffer: refill it with the current policy before updating again.
            refill = max(self.init_random_frames, int(self.cfg.algo.batch_size))
            self.update_start_frames = self.tracker.frames + refill
            total = int(self.cfg.total_frames)
            none = total <= self.update_start_frames and self.tracker.frames < total
            print(
                f"resume: the replay buffer was not saved (save_replay_buffer=false); the "
                f"next {refill} frames refill it, no update before frame "
                f"{self.update_start_frames}"
                + (f"; this session stops at total_frames={total}: no update" if none else ""),
                flush=True,
            )
