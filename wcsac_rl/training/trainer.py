"""The off-policy training loop (WCSAC, SAC-Lag, SAC) and the random-policy baseline.

One collector batch (``algo.collector.frames_per_batch`` frames from the batched
training envs) is followed by ``frames_per_batch × utd_ratio`` gradient steps on
replay samples; every ``epoch_frames`` frames one row of metrics is logged and
deterministic test episodes are run; checkpoints are written every
``checkpoint_every_epochs`` epochs, at the end, and on Ctrl-C.
"""

from __future__ import annotations

import math
import random
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl import timeit
from tqdm.auto import tqdm

from wcsac_rl.evaluation.episodes import run_episodes, summarize_episodes
from wcsac_rl.training import builders
from wcsac_rl.training.checkpoint import (
    CHECKPOINT_DIR,
    LAST_CHECKPOINT,
    REPLAY_BUFFER_DIR,
    check_compatible,
    find_checkpoint,
    load_checkpoint,
    save_checkpoint,
)
from wcsac_rl.training.config import ConfigError, validate_config
from wcsac_rl.training.progress import EpisodeTracker, ProgressWriter

__all__ = ["Trainer", "seed_everything"]


def seed_everything(seed: int) -> None:
    """Seed Python, NumPy and torch (the envs and collector are seeded by their builders)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


class Trainer:
    """A training run built from a Hydra config; ``run()`` trains and returns the run dir.

    Args:
        cfg: the composed config (``conf/config.yaml``).
        run_dir: where logs, ``progress.csv`` and checkpoints go. With
            ``cfg.resume`` set, the resumed run's directory is used instead.
    """

    def __init__(self, cfg: DictConfig, run_dir: str | Path) -> None:
        validate_config(cfg)
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        checkpoint = self._resume_checkpoint()
        torch.set_num_threads(int(cfg.threads))
        seed_everything(int(cfg.seed))

        from wcsac_rl.envs import env_info

        self.max_episode_steps = int(
            env_info(cfg.env.name, **builders._env_kwargs(cfg))["max_episode_steps"]
        )
        self.env = builders.make_train_env(cfg)
        self.eval_env = builders.make_eval_env(cfg) if cfg.eval_episodes > 0 else None
        self.learning = cfg.algo.name != "random"
        collector_cfg = cfg.algo.collector
        if self.learning:
            self.agent = builders.make_agent(cfg, self.env)
            self.loss = builders.make_loss(cfg, self.agent, self.max_episode_steps)
            self.target_updater = builders.make_target_updater(cfg, self.loss)
            self.optimizers = builders.make_optimizers(cfg, self.loss)
            self.replay_buffer = builders.make_replay_buffer(cfg)
            self.updates_per_batch = max(
                1, round(int(collector_cfg.frames_per_batch) * float(collector_cfg.utd_ratio))
            )
            self.init_random_frames = int(collector_cfg.init_random_frames)
            # frames after which gradient steps start (moved on resume, see _load_state)
            self.update_start_frames = self.init_random_frames
            self.policy = self.agent.actor
            self._loss_forward = self._compiled_loss() if cfg.compile else self.loss
        else:
            self.policy = None
            self.init_random_frames = 0

        self.updates = 0
        self.epoch = 0
        self.elapsed = 0.0  # training wall time over all sessions of this run
        self.tracker = EpisodeTracker()
        if checkpoint is not None:
            self._load_state(checkpoint)
        remaining = max(0, int(cfg.total_frames) - self.tracker.frames)
        self.collector = (
            builders.make_collector(
                cfg,
                self.env,
                self.policy,
                total_frames=remaining,
                init_random_frames=max(0, self.init_random_frames - self.tracker.frames),
            )
            if remaining > 0
            else None
        )
        self.logger = builders.make_logger(cfg, self.run_dir)
        self.progress = ProgressWriter(self.run_dir / "progress.csv")
        OmegaConf.save(cfg, self.run_dir / "config.yaml", resolve=True)

    # ------------------------------------------------------------- set-up
    @property
    def checkpoint_path(self) -> Path:
        return self.run_dir / CHECKPOINT_DIR / LAST_CHECKPOINT

    def _resume_checkpoint(self) -> dict[str, Any] | None:
        cfg = self.cfg
        if cfg.resume:
            path = find_checkpoint(cfg.resume)
            checkpoint = load_checkpoint(path)
            check_compatible(checkpoint["config"], cfg, path)
            self.run_dir = path.parent.parent
            return checkpoint
        if self.checkpoint_path.exists():
            raise ConfigError(
                f"{self.run_dir} already holds a run (checkpoint {self.checkpoint_path}); "
                f"continue it with resume={self.run_dir} or choose another directory"
            )
        self.run_dir.mkdir(parents=True, exist_ok=True)
        return None

    def _compiled_loss(self):
        try:
            return torch.compile(self.loss)
        except Exception as err:  # pragma: no cover - depends on the platform's compiler
            print(f"torch.compile unavailable ({err}); training eagerly")
            return self.loss

    # ------------------------------------------------------------- update
    def update(self, batch: TensorDictBase) -> TensorDictBase:
        """One gradient step on every parameter group, then the polyak update of the targets.

        Each loss term reaches only its own parameters, so one backward of their sum
        equals separate backwards; all terms are computed from the same parameters
        (critics, actor, β and κ are then stepped together).
        """
        out = self._loss_forward(batch)
        total = sum(value for key, value in out.items() if key.startswith("loss_"))
        total.backward()
        for optimizer in self.optimizers.values():
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        self.target_updater.step()
        self.updates += 1
        return out.detach()

    # ----------------------------------------------------------------- loop
    def run(self) -> Path:
        """Train to ``total_frames``. Ctrl-C writes a checkpoint, then re-raises."""
        cfg = self.cfg
        if self.collector is None:
            print(
                f"{self.run_dir}: already trained for {self.tracker.frames} frames; nothing to do"
            )
            return self.run_dir
        epoch_frames = int(cfg.epoch_frames)
        next_epoch_end = (self.tracker.frames // epoch_frames + 1) * epoch_frames
        loss_outputs: list[TensorDictBase] = []
        epoch_start, epoch_start_frames, epoch_start_updates = (
            time.time(),
            self.tracker.frames,
            self.updates,
        )
        timeit.erase()
        pbar = tqdm(
            total=int(cfg.total_frames),
            initial=self.tracker.frames,
            disable=not cfg.progress_bar,
            unit="frames",
            desc=f"{cfg.algo.name} {cfg.env.name} seed {cfg.seed}",
        )
        try:
            collector_iter = iter(self.collector)
            while True:
                with timeit("collect"):
                    batch = next(collector_iter, None)
                if batch is None:
                    break
                self.tracker.add(batch)
                pbar.update(batch.numel())
                if self.learning:
                    with timeit("replay_extend"):
                        self.replay_buffer.extend(batch.reshape(-1))
                    if self.tracker.frames >= self.update_start_frames:
                        with timeit("update"):
                            for _ in range(self.updates_per_batch):
                                loss_outputs.append(self.update(self.replay_buffer.sample()))
                if self.tracker.frames >= next_epoch_end or self.tracker.frames >= cfg.total_frames:
                    seconds = time.time() - epoch_start
                    self.elapsed += seconds
                    self.epoch += 1
                    row = self._epoch_row(
                        loss_outputs,
                        seconds,
                        self.tracker.frames - epoch_start_frames,
                        self.updates - epoch_start_updates,
                    )
                    self._log(row)
                    pbar.set_postfix(
                        ret=f"{row['train/episode_return']:.2f}",
                        cost=f"{row['train/episode_cost']:.1f}",
                    )
                    if self.epoch % int(cfg.checkpoint_every_epochs) == 0:
                        self.save()
                    loss_outputs = []
                    next_epoch_end += epoch_frames
                    epoch_start = time.time()
                    epoch_start_frames, epoch_start_updates = self.tracker.frames, self.updates
        except KeyboardInterrupt:
            self.elapsed += time.time() - epoch_start
            self.save()
            pbar.close()
            print(f"\ninterrupted: checkpoint written to {self.checkpoint_path}")
            raise
        finally:
            pbar.close()
            self.collector.shutdown()
        self.save()
        return self.run_dir

    def _epoch_row(
        self, loss_outputs: list[TensorDictBase], seconds: float, frames: int, updates: int
    ) -> dict[str, float]:
        row: dict[str, float] = {
            "epoch": self.epoch,
            "frames": self.tracker.frames,
            "updates": self.updates,
            "time_s": round(self.elapsed, 3),
        }
        row.update(self.tracker.epoch_metrics())
        self.tracker.reset_epoch()
        if self.learning:
            row.update(self._loss_means(loss_outputs))
        with timeit("eval"):
            row.update(self._evaluate())
        row["time/fps"] = frames / seconds if seconds > 0 else math.nan
        row["time/ups"] = updates / seconds if seconds > 0 else math.nan
        for name, total in timeit.todict(percall=False).items():
            row[f"time/{name}_s"] = total
        timeit.erase()
        return row

    def _loss_means(self, outputs: list[TensorDictBase]) -> dict[str, float]:
        keys = [*self.loss.out_keys]
        if not outputs:
            return {f"loss/{key}": math.nan for key in keys}
        stacked = torch.stack([td.select(*keys) for td in outputs]).float().mean(0)
        return {f"loss/{key}": float(stacked[key]) for key in keys}

    def _evaluate(self) -> dict[str, float]:
        if self.eval_env is None:
            return {}
        episodes = run_episodes(
            self.eval_env,
            self.policy,
            int(self.cfg.eval_episodes),
            deterministic=True,
            max_steps=self.max_episode_steps,
        )
        return {f"eval/{k}": v for k, v in summarize_episodes(episodes).items()}

    def _log(self, row: dict[str, float]) -> None:
        self.progress.write(row)
        if self.logger is not None:
            for key, value in row.items():
                if key not in ("epoch", "frames") and not (
                    isinstance(value, float) and math.isnan(value)
                ):
                    self.logger.log_scalar(key, value, step=int(row["frames"]))

    # ---------------------------------------------------------- checkpoint
    def state_dict(self) -> dict[str, Any]:
        state: dict[str, Any] = {
            "config": OmegaConf.to_container(self.cfg, resolve=True),
            "frames": self.tracker.frames,
            "total_cost": self.tracker.total_cost,
            "updates": self.updates,
            "epoch": self.epoch,
            "elapsed": self.elapsed,
            "rng": {
                "torch": torch.get_rng_state(),
                "numpy": np.random.get_state(),
                "python": random.getstate(),
            },
        }
        if self.learning:
            state["loss"] = self.loss.state_dict()
            state["optimizers"] = {k: opt.state_dict() for k, opt in self.optimizers.items()}
        return state

    def save(self) -> Path:
        """Write ``checkpoints/last.pt`` (and the replay buffer if configured)."""
        if self.learning and self.cfg.save_replay_buffer and len(self.replay_buffer):
            buffer_dir = self.run_dir / CHECKPOINT_DIR / REPLAY_BUFFER_DIR
            buffer_dir.parent.mkdir(parents=True, exist_ok=True)
            self.replay_buffer.dumps(buffer_dir)
        save_checkpoint(self.checkpoint_path, self.state_dict())
        return self.checkpoint_path

    def _load_state(self, state: dict[str, Any]) -> None:
        self.tracker = EpisodeTracker(
            frames=int(state["frames"]), total_cost=float(state["total_cost"])
        )
        self.updates = int(state["updates"])
        self.epoch = int(state["epoch"])
        self.elapsed = float(state.get("elapsed", 0.0))
        if self.learning:
            self.loss.load_state_dict(state["loss"])
            for key, optimizer in self.optimizers.items():
                optimizer.load_state_dict(state["optimizers"][key])
            buffer_dir = self.run_dir / CHECKPOINT_DIR / REPLAY_BUFFER_DIR
            if buffer_dir.exists():
                self.replay_buffer.loads(buffer_dir)
                self.update_start_frames = 0
            else:
                # No saved buffer: refill it with the current policy before updating again.
                refill = max(self.init_random_frames, int(self.cfg.algo.batch_size))
                self.update_start_frames = self.tracker.frames + refill
        rng = state["rng"]
        torch.set_rng_state(rng["torch"])
        np.random.set_state(rng["numpy"])
        random.setstate(rng["python"])

    def close(self) -> None:
        """Release envs and flush the logger."""
        for env in (self.env, self.eval_env):
            if env is not None and not env.is_closed:
                env.close()
        experiment = getattr(self.logger, "experiment", None)
        if hasattr(experiment, "finish"):
            experiment.finish()
