"""The training loop shared by every algorithm: collect, learn, log, evaluate, checkpoint.

:class:`Trainer` owns the run: the batched training envs and TorchRL ``Collector``,
episode statistics, one ``progress.csv`` row (and logger scalars) per epoch of
``epoch_frames`` frames, deterministic test episodes, checkpoints (every
``checkpoint_every_epochs`` epochs, at the end and on Ctrl-C) and resume. What an
algorithm does with a collected batch is its subclass's :meth:`Trainer.learn`
(:class:`~wcsac_rl.training.off_policy.OffPolicyTrainer` for WCSAC, SAC-Lag and SAC,
:class:`RandomPolicyTrainer` for the random baseline); :func:`make_trainer` picks it.
"""

from __future__ import annotations

import contextlib
import errno
import math
import random
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torchrl import timeit
from torchrl.envs import EnvBase
from tqdm.auto import tqdm

from wcsac_rl._messages import first_line
from wcsac_rl.envs import CostKeyError, EnvSourceError, NonFiniteStepError
from wcsac_rl.envs.presets import has_goals
from wcsac_rl.objectives.inputs import nonfinite_entry
from wcsac_rl.rollouts import critic_calibration as calibration
from wcsac_rl.rollouts.episodes import run_episodes, summarize_episodes
from wcsac_rl.training import builders, schedule
from wcsac_rl.training.checkpoint import (
    CHECKPOINT_DIR,
    LAST_CHECKPOINT,
    StateMismatch,
    check_compatible,
    check_counters,
    check_not_behind,
    check_resume_changes,
    check_run_config,
    find_checkpoint,
    keep_checkpoint,
    load_checkpoint,
    numpy_rng_state,
    save_checkpoint,
    set_numpy_rng_state,
    write_error_reason,
)
from wcsac_rl.training.config import ConfigError, TrainingError, validate_config
from wcsac_rl.training.config_keys import check_known_keys, key_paths
from wcsac_rl.training.preemption import Preempted, StopSignals, how_to_continue
from wcsac_rl.training.progress import EpisodeTracker, LossMeans, ProgressWriter, read_progress
from wcsac_rl.training.provenance import session_provenance, write_provenance
from wcsac_rl.training.run_dir import (
    AUTO_RESUME,
    RunLock,
    check_new_run_dir,
    check_own_files,
    check_progress_rows,
    check_restartable_run_dir,
    cut_records_to,
    discard_unused_run_dir,
    own_copies,
    replace_text,
)
from wcsac_rl.training.runtime import retain_freed_memory
from wcsac_rl.training.training_safety import TrainingSafety, training_safety

__all__ = ["RandomPolicyTrainer", "Trainer", "seed_everything"]

# a run's own files cannot be written: disk full, quota, read-only, permissions
WRITE_ERRNOS = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC), errno.EROFS, errno.EACCES}

COLLECTED_ENTRIES = (("next", "cost"), ("next", "reward"), ("next", "observation"), "observation")
"""What a collected batch must hold finite numbers in (checked once per batch)."""

RESUME_ENTRIES = ("config", "frames", "total_cost", "updates", "epoch", "rng", "learner")
"""What a checkpoint must hold to resume a run (:meth:`Trainer.state_dict`)."""

EVAL_ENVS = 10
"""Most test episodes run side by side (each one sub-env of one in-process batch)."""


def seed_everything(seed: int) -> None:
    """Seed Python, NumPy and torch (the envs and collector are seeded by their builders)."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def _logger_state(checkpoint: dict[str, Any] | None, backend: str) -> dict | None:
    """The checkpoint's logger state if it was written by the same logger backend."""
    saved = None if checkpoint is None else checkpoint.get("logger")
    if not saved or saved.get("backend") != backend:
        return None
    return saved.get("state")


def env_max_episode_steps(cfg: DictConfig) -> int:
    """Episode length of the run's environment (config override or the preset's); for
    ``env=gymnasium`` the user's env is built and stepped once here, so that an id that
    does not resolve, an env that raises or reports no cost is refused (one line) before
    a run starts."""
    from wcsac_rl.envs import env_info

    try:
        return int(env_info(cfg.env.name, **builders.env_kwargs(cfg))["max_episode_steps"])
    except (EnvSourceError, CostKeyError) as err:
        raise ConfigError(str(err)) from None
    except (TypeError, ValueError) as err:  # a preset's constructor: an option it lacks
        raise ConfigError(f"env.kwargs of env={cfg.env.name}: {first_line(err)}") from None


def _postfix(row: dict[str, float]) -> str:
    """The progress bar's epoch summary: the epoch's training episodes (when one finished),
    the run's cumulative training cost and its epochs over the cost limit d so far."""
    safety = (
        f"cum_cost={row['train/cumulative_cost']:.0f}, "
        f"epochs>d={int(row['train/epochs_over_limit'])}"
    )
    if not row["train/episodes"]:  # episodes longer than the epoch so far
        return f"no finished episode, {safety}"
    return f"ret={row['train/episode_return']:.2f}, cost={row['train/episode_cost']:.1f}, {safety}"


def _resumes_a_path(cfg: DictConfig) -> bool:
    return bool(cfg.get("resume")) and cfg.resume != AUTO_RESUME


class Trainer:
    """A training run built from a Hydra config; ``run()`` trains and returns the run dir.

    Args:
        cfg: the composed config (``conf/config.yaml``).
        run_dir: where logs, ``progress.csv`` and checkpoints go. With
            ``cfg.resume`` set, the resumed run's directory is used instead.
        overrides: the command line's overrides that composed ``cfg`` (``train.py``
            passes Hydra's), recorded in the session's ``provenance.json`` beside the
            code's commit (:mod:`~wcsac_rl.training.provenance`).
    """

    def __init__(
        self, cfg: DictConfig, run_dir: str | Path, *, overrides: Sequence[str] | None = None
    ) -> None:
        # (a resumed run's keys are checked against its checkpoint: _check_resumable)
        validate_config(cfg, check_keys=not _resumes_a_path(cfg))
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.overrides = None if overrides is None else list(overrides)
        self.lock: RunLock | None = None
        self._resumed_from: Path | None = None  # the checkpoint a resume continues
        self.env = self.eval_env = self.logger = None
        fresh = not self.run_dir.exists()  # (made by this call: removed again if refused)
        try:
            self._set_up(self._resume_checkpoint())
        except BaseException:
            self.close()  # releases the run directory's lock too
            if fresh and self.run_dir == Path(run_dir):  # (it holds no more than its lock)
                with contextlib.suppress(OSError):  # (another process wrote into it meanwhile)
                    discard_unused_run_dir(self.run_dir)
            raise

    def _set_up(self, checkpoint: dict[str, Any] | None) -> None:
        cfg = self.cfg
        torch.set_num_threads(int(cfg.threads))
        if cfg.get("retain_freed_memory", False):
            retain_freed_memory()
        seed_everything(int(cfg.seed))

        self.max_episode_steps = env_max_episode_steps(cfg)
        # epochs after which checkpoints/frames-<N>.pt is kept (Figure 5's stages)
        self.keep_epochs = frozenset(int(e) for e in (cfg.get("keep_checkpoints_at") or ()))
        self.logger = None
        self.env = builders.make_train_env(cfg)
        # the test episodes of an epoch run side by side (up to EVAL_ENVS at a time)
        self.eval_env = (
            builders.make_eval_env(cfg, num_envs=min(int(cfg.eval_episodes), EVAL_ENVS))
            if cfg.eval_episodes > 0
            else None
        )
        self.policy = None  # set by _build_learner; None acts uniformly at random
        self.collection_policy = None  # set by _build_learner if it differs (a shield)
        self.init_random_frames = 0  # collector frames with random actions at the start
        self._build_learner()

        self.updates = 0
        self.skipped_updates = 0  # updates not taken: non-finite loss or gradient (whole run)
        self.epoch_skipped_updates = 0
        self.nonfinite_streak = 0  # ... of which the last ones in a row
        self.epoch = 0
        self.elapsed = 0.0  # training wall time over all sessions of this run
        self.tracker = EpisodeTracker(goals=has_goals(cfg.env.name))
        self.training_safety = TrainingSafety(float(cfg.cost_limit))  # running over the run
        # the epoch in progress (carried over by a checkpoint taken mid-epoch)
        self.loss_means = LossMeans(self.loss_keys)
        self.epoch_start_frames = self.epoch_start_updates = 0
        self.epoch_seconds = 0.0  # of the epoch in progress, in earlier sessions
        self._epoch_clock: float | None = None  # when this session's part of it began
        self._checkpoint_frames: int | None = None  # frames of this session's last save
        if checkpoint is not None:
            self._load_state(checkpoint)
            try:
                self.load_learner_state(checkpoint.get("learner", {}))
            except StateMismatch as err:
                raise ConfigError(f"checkpoint {self._resumed_from}: {err}") from None
            self._own_copies()
            # rows logged after this checkpoint (by a session killed before its next
            # checkpoint) are dropped: the resumed session logs those epochs again
            dropped = cut_records_to(self.run_dir, epoch=self.epoch, frames=self.tracker.frames)
            if dropped:
                print(
                    f"{self.run_dir}: dropped {dropped} progress.csv row(s) logged after the "
                    f"checkpoint (epoch {self.epoch}, {self.tracker.frames} frames)"
                )
        remaining = max(0, int(cfg.total_frames) - self.tracker.frames)
        notes = schedule.schedule_notes(
            cfg, frames_done=self.tracker.frames, init_random_frames=self.init_random_frames
        )
        for note in notes:  # whole collector batches (stdout); a warm-up-only budget (stderr)
            print(note, file=sys.stderr if note.startswith("warning:") else sys.stdout, flush=True)
        self.collector = (
            builders.make_collector(
                cfg,
                self.env,
                self.collector_policy(),
                total_frames=remaining,
                init_random_frames=max(0, self.init_random_frames - self.tracker.frames),
                # a resumed run must not replay the episodes its first session started with
                seed=int(cfg.seed) + self.tracker.frames,
            )
            if remaining > 0
            else None
        )
        self.logger = builders.make_logger(
            cfg,
            self.run_dir,
            state=_logger_state(checkpoint, str(cfg.logger.backend)),
            resume_frames=None if checkpoint is None else self.tracker.frames,
        )
        self.progress = ProgressWriter(self.run_dir / "progress.csv")
        if checkpoint is not None:
            # after building the collector and the logger (they draw from the global RNGs)
            self._restore_rng(checkpoint["rng"], self._resumed_from)
        # a session's records, once nothing can refuse it (a resume of a finished run
        # trains nothing: it writes none)
        self.config_path = self.provenance_path = None
        if checkpoint is None or self.collector is not None:
            self.config_path = self._write_config(resumed=checkpoint is not None)
            self.provenance_path = write_provenance(
                self.run_dir,
                session_provenance(
                    overrides=self.overrides,
                    threads=int(cfg.threads),
                    resumed_from_frames=None if checkpoint is None else self.tracker.frames,
                ),
                resumed=checkpoint is not None,
            )

    def _write_config(self, *, resumed: bool) -> Path:
        """``config.yaml`` for a new run; a resumed session never rewrites it but writes
        its own beside it (``config.resume1.yaml``, ``config.resume2.yaml``, ...)."""
        path = self.run_dir / "config.yaml"
        if resumed and path.exists():
            k = 1
            while (path := self.run_dir / f"config.resume{k}.yaml").exists():
                k += 1
        replace_text(path, OmegaConf.to_yaml(self.cfg, resolve=True))
        return path

    # ------------------------------------------------------------- set-up
    @property
    def checkpoint_path(self) -> Path:
        return self.run_dir / CHECKPOINT_DIR / LAST_CHECKPOINT

    def _resume_checkpoint(self) -> dict[str, Any] | None:
        """Take the run directory's lock; return the checkpoint to resume (``None``: new run)."""
        cfg = self.cfg
        if cfg.get("resume") is not None and not str(cfg.resume).strip():
            raise ConfigError(  # (`resume=$RUN` with RUN unset: never a new run instead)
                f"resume={cfg.resume!r} names no run: give resume=<run directory>, "
                "resume=<run dir>/checkpoints/<file>.pt or resume=auto, or leave resume out "
                "for a new run"
            )
        if cfg.resume == AUTO_RESUME:
            return self._auto_resume_checkpoint()
        if cfg.resume:
            given = Path(str(cfg.resume)).expanduser()
            if given.is_dir():  # lock first: no other run may be writing it
                self.lock = RunLock(given)
            path = find_checkpoint(given)
            self.run_dir = path.parent.parent
            if self.lock is None:
                self.lock = RunLock(self.run_dir)
            checkpoint = load_checkpoint(path, required=RESUME_ENTRIES)
            self._check_resumable(checkpoint, path)
            check_not_behind(path, int(checkpoint["frames"]), self.run_dir)
            return checkpoint
        self.lock = RunLock(self.run_dir)
        check_new_run_dir(self.run_dir)
        return None

    def _auto_resume_checkpoint(self) -> dict[str, Any] | None:
        """``resume=auto``: continue the run in this run directory from its checkpoint (the
        config composed now, checked as on any resume), or start it there if it has none (what
        re-running a sweep does for each of its jobs; docs/training.md).
        """
        self.lock = RunLock(self.run_dir)
        path = self.checkpoint_path
        if not path.is_file():
            check_restartable_run_dir(self.run_dir)
            self._own_copies()
            return None
        checkpoint = load_checkpoint(path, required=RESUME_ENTRIES)
        self._check_resumable(checkpoint, path)
        print(f"{self.run_dir}: resuming from {path} ({int(checkpoint['frames'])} frames)")
        return checkpoint

    def _own_copies(self) -> None:
        """A run copied with hard links (``cp -al``) shares its files with the original:
        each gets a copy of its own before this session writes (:func:`own_copies`)."""
        copied = own_copies(self.run_dir)
        if copied:
            print(
                f"{self.run_dir}: {len(copied)} file(s) shared with another path by hard "
                "links (a copy made with cp -al?) now have their own copies; what this "
                "session writes stays in this run"
            )

    def _check_resumable(self, checkpoint: dict[str, Any], path: Path) -> None:
        """What every resume verifies before it writes anything (docs/guarantees.md, "What a
        resume verifies"): the checkpoint's config against the session's and the run's own
        record, what may change, its counters and the run's records.
        """
        self._resumed_from = path
        check_own_files(self.run_dir)
        check_compatible(checkpoint["config"], self.cfg, path)
        check_run_config(checkpoint["config"], self.run_dir, path)
        # keys the run was saved with are its own (an option since removed included)
        check_known_keys(self.cfg, extra=key_paths(checkpoint["config"]))
        check_resume_changes(checkpoint["config"], self.cfg, path)
        check_counters(checkpoint, path)
        check_progress_rows(self.run_dir, checkpoint["epoch"])

    # ---------------------------------------------------------- algorithm
    def _build_learner(self) -> None:
        """Build the algorithm's networks, loss and optimizers; set ``self.policy`` (and
        ``self.collection_policy`` when the collector acts through something else)."""

    def collector_policy(self) -> TensorDictModuleBase | None:
        """What the collector acts with: ``self.collection_policy`` if set, else
        ``self.policy``."""
        return self.policy if self.collection_policy is None else self.collection_policy

    def learn(self, batch: TensorDictBase) -> list[TensorDictBase]:
        """Learn from one collected batch; return the loss outputs to average per epoch."""
        return []

    def observe_training_episodes(self, metrics: dict[str, float]) -> None:
        """The epoch's ``train/*`` episode statistics, for a learner that reads them."""

    def collection_metrics(self) -> dict[str, float]:
        """The epoch's ``train/*`` columns about how the learner collected (a shield's
        rate), then reset for the next epoch; fixed keys for a run."""
        return {}

    def learner_state(self) -> dict[str, Any]:
        """What a checkpoint must hold to resume the algorithm (networks, optimizers...)."""
        return {}

    def load_learner_state(self, state: dict[str, Any]) -> None:
        """Restore :meth:`learner_state` (called after the run counters are restored)."""

    @classmethod
    def restore_policy(
        cls, cfg: DictConfig, learner_state: dict[str, Any], env: EnvBase
    ) -> TensorDictModule | None:
        """The trained policy from a checkpoint's ``learner`` state (``None``: random actions).

        ``env`` is an env of the run's preset (for specs). Used by evaluation.
        """
        return None

    # ----------------------------------------------------------------- loop
    def run(self) -> Path:
        """Train to ``total_frames``. Ctrl-C writes a checkpoint, then re-raises; a stop
        signal (``SIGTERM``, ``SIGUSR1``, ``SIGUSR2``: :mod:`~wcsac_rl.training.preemption`)
        writes a checkpoint at the next batch boundary, then raises
        :class:`~wcsac_rl.training.preemption.Preempted` (or exits through the
        scheduler's own handler)."""
        cfg = self.cfg
        if self.collector is None:
            print(
                f"{self.run_dir}: already trained for {self.tracker.frames} frames; nothing to do"
            )
            return self.run_dir
        self._epoch_clock = time.time()
        timeit.erase()
        pbar = tqdm(
            total=int(cfg.total_frames),
            initial=self.tracker.frames,
            disable=not cfg.progress_bar,
            unit="frames",
            desc=f"{cfg.algo.name} {cfg.env.name} seed {cfg.seed}",
        )
        try:
            with StopSignals() as stop:  # SIGTERM / SIGUSR1 / SIGUSR2: checkpoint, then stop
                self._train(pbar, stop)
                self.save()  # the final checkpoint (a stop signal now finds the run complete)
        except KeyboardInterrupt:
            self._save_interrupted()  # with the epoch in progress: the resumed session completes its row
            pbar.close()
            how = how_to_continue(self.run_dir, resume_auto=self.cfg.resume == AUTO_RESUME)
            print(
                f"\ninterrupted at {self.tracker.frames} frames; checkpoint written to "
                f"{self.checkpoint_path}: {how}",
                file=sys.stderr,
                flush=True,
            )
            raise
        except OSError as err:
            if err.errno not in WRITE_ERRNOS:
                raise
            raise TrainingError(
                f"cannot write to {self.run_dir}: {write_error_reason(err, self.run_dir)}; "
                f"the last checkpoint {self.checkpoint_path} is kept (free some space, then "
                f"resume={self.run_dir})"
            ) from None
        finally:
            pbar.close()
            self.collector.shutdown()
        if stop.received is not None:  # in the last batch or the final checkpoint
            print(
                f"{signal.Signals(stop.received).name}: the run is complete "
                f"({self.tracker.frames} frames); checkpoint written to {self.checkpoint_path}",
                flush=True,
            )
        return self.run_dir

    def _save_interrupted(self) -> None:
        """Checkpoint mid-epoch (Ctrl-C, a stop signal): the epoch in progress is saved
        with it, so the resumed session logs that epoch once, in full."""
        session = time.time() - self._epoch_clock
        self.elapsed += session
        self.epoch_seconds, self._epoch_clock = self.epoch_seconds + session, time.time()
        self.save()

    def _train(self, pbar: tqdm, stop: StopSignals) -> None:
        """The loop of :meth:`run`: collect, learn, log and checkpoint each epoch; after a
        stop signal, checkpoint at the next batch boundary and stop (:class:`Preempted`)."""
        cfg = self.cfg
        epoch_frames = schedule.epoch_frames(cfg)  # whole collector batches
        next_epoch_end = (self.tracker.frames // epoch_frames + 1) * epoch_frames
        collector_iter = iter(self.collector)
        while True:
            with timeit("collect"):
                batch = self._next_batch(collector_iter)
            if batch is None:
                break
            self.tracker.add(batch)
            pbar.update(batch.numel())
            self.loss_means.add(self.learn(batch))
            if self.tracker.frames >= next_epoch_end or self.tracker.frames >= cfg.total_frames:
                session = time.time() - self._epoch_clock
                self.elapsed += session
                self.epoch += 1
                row = self._epoch_row(
                    self.loss_means,
                    self.epoch_seconds + session,
                    self.tracker.frames - self.epoch_start_frames,
                    self.updates - self.epoch_start_updates,
                )
                self._log(row)
                # a new epoch begins (before the checkpoint, which must not carry
                # the finished epoch's sums over)
                self.loss_means.reset()
                self.epoch_seconds, self._epoch_clock = 0.0, time.time()
                self.epoch_start_frames, self.epoch_start_updates = (
                    self.tracker.frames,
                    self.updates,
                )
                pbar.set_postfix_str(_postfix(row))
                keep = self.epoch in self.keep_epochs
                if keep or self.epoch % int(cfg.checkpoint_every_epochs) == 0:
                    self.save()
                if keep:
                    keep_checkpoint(self.checkpoint_path, self.tracker.frames)
                next_epoch_end += epoch_frames
            if stop.received is not None and self.tracker.frames < cfg.total_frames:
                if self._checkpoint_frames != self.tracker.frames:  # (the signal may have
                    self._save_interrupted()  # come during this epoch's checkpoint)
                pbar.close()
                print(
                    f"\n{signal.Signals(stop.received).name}: checkpoint written to "
                    f"{self.checkpoint_path}",
                    flush=True,
                )
                stop.forward()  # a scheduler's handler (submitit: requeue) may exit here
                raise Preempted(
                    stop.received,
                    self.checkpoint_path,
                    self.tracker.frames,
                    resume_auto=cfg.resume == AUTO_RESUME,
                )

    def _kept_checkpoint(self) -> str:
        if self.checkpoint_path.is_file():
            return f"the last checkpoint {self.checkpoint_path} is kept"
        return "no checkpoint had been written yet"

    def _next_batch(self, batches) -> TensorDictBase | None:
        """The next collected batch (``None``: the run is done), refused with one line
        naming the entry and the frames when a reward, cost or observation in it is not
        finite: it never reaches the replay buffer, and the last checkpoint stays."""
        start = self.tracker.frames
        try:
            batch = next(batches, None)
        except (NonFiniteStepError, CostKeyError, EnvSourceError) as err:  # the env's words
            # (an env under RejectNonFinite; your env: a step without a cost)
            error = NonFiniteStepError if isinstance(err, NonFiniteStepError) else TrainingError
            raise error(
                f"{err}; training stopped while collecting the frames after {start} "
                f"({self._kept_checkpoint()})"
            ) from None
        if batch is None:
            return None
        found = nonfinite_entry(batch, COLLECTED_ENTRIES)
        if found is not None:
            key, count, total, first = found
            raise TrainingError(
                f"the batch collected at frames {start}-{start + batch.numel()} holds a "
                f"non-finite {key!r} ({count} of {total} values, e.g. {first}); training "
                f"stopped before it reached the replay buffer ({self._kept_checkpoint()}). "
                "Check the env's rewards, costs and observations"
            )
        return batch

    def _epoch_row(
        self, loss_means: LossMeans, seconds: float, frames: int, updates: int
    ) -> dict[str, float]:
        row: dict[str, float] = {
            "epoch": self.epoch,
            "frames": self.tracker.frames,
            "updates": self.updates,
            "time_s": round(self.elapsed, 3),
        }
        row.update(self.tracker.epoch_metrics())
        self.tracker.reset_epoch()
        self.observe_training_episodes(row)
        self.training_safety.add_epoch(
            self.tracker.frames, row["train/episode_cost"], self.tracker.total_cost
        )
        row.update(self.training_safety.columns())
        row["train/skipped_updates"] = self.epoch_skipped_updates
        self.epoch_skipped_updates = 0
        row.update(self.collection_metrics())
        row.update(loss_means.means())
        if "loss/cost_threshold" in row and "loss/cvar" in row:
            # what the κ loss pushes on: > 0 lets κ shrink, < 0 makes it grow
            held = row.get("loss/constraint_cvar", row["loss/cvar"])  # (kappa_signal)
            row["loss/constraint_slack"] = row["loss/cost_threshold"] - held
        with timeit("eval"):
            try:
                row.update(self._evaluate())
            except (CostKeyError, EnvSourceError) as err:  # your env, in a test episode
                raise TrainingError(
                    f"{err}; training stopped in the test episodes at {self.tracker.frames} "
                    f"frames ({self._kept_checkpoint()})"
                ) from None
        row["time/fps"] = frames / seconds if seconds > 0 else math.nan
        row["time/ups"] = updates / seconds if seconds > 0 else math.nan
        for name, total in timeit.todict(percall=False).items():
            row[f"time/{name}_s"] = total
        timeit.erase()
        return row

    @property
    def loss_keys(self) -> list[str]:
        """The loss outputs logged as ``loss/<key>`` (fixed, so every row has them)."""
        return []

    def _evaluate(self) -> dict[str, float]:
        """The epoch's deterministic test episodes: ``eval/*`` means and, when the
        learner's loss has a safety critic, its calibration on those very episodes
        (``calib/*``, :mod:`wcsac_rl.rollouts.critic_calibration`)."""
        if self.eval_env is None:
            return {}
        loss = getattr(self, "loss", None)
        episodes, calib = int(self.cfg.eval_episodes), {}
        if calibration.supports_calibration(loss):
            recorded = calibration.record_calibration_episodes(
                self.eval_env, self.policy, loss, episodes, max_steps=self.max_episode_steps
            )
            results = [episode.result for episode in recorded]
            calib = calibration.calibration_metrics(recorded, loss)
        else:
            results = run_episodes(
                self.eval_env,
                self.policy,
                episodes,
                deterministic=True,
                max_steps=self.max_episode_steps,
            )
        self.observe_test_episodes(results)
        row = {f"eval/{k}": v for k, v in summarize_episodes(results).items()}
        # the share of test episodes that reached a goal (an env with goals)
        if has_goals(self.cfg.env.name):
            reached = [r.goal_reached > 0 for r in results]
            row["eval/goal_rate"] = sum(reached) / len(reached) if reached else math.nan
        return {**row, **calib}

    def observe_test_episodes(self, results: list) -> None:
        """The epoch's test episodes (``EpisodeResult``), for a learner that reads them."""

    def _log(self, row: dict[str, float]) -> None:
        self.progress.write(row)
        if self.logger is not None:
            for key, value in row.items():
                if key not in ("epoch", "frames") and not (
                    isinstance(value, float) and math.isnan(value)
                ):
                    self.logger.log_scalar(key, value, step=int(row["frames"]))

    def skip_update(self, what: str) -> None:
        """Count an update not taken because ``what`` was not finite (NaN or inf).

        Raises :class:`TrainingError` once ``max_nonfinite_updates`` updates in a row
        were skipped (the last checkpoint, if one was written, is kept).
        """
        self.skipped_updates += 1
        self.epoch_skipped_updates += 1
        self.nonfinite_streak += 1
        limit = self.cfg.get("max_nonfinite_updates")
        if limit is not None and self.nonfinite_streak >= int(limit):
            raise TrainingError(
                f"{self.nonfinite_streak} updates in a row had a non-finite {what} and were "
                f"skipped (at {self.tracker.frames} frames, {self.skipped_updates} skipped in "
                f"all; {self._kept_checkpoint()}). Check the algorithm's options (a "
                "multiplier or scale near its ceiling), the env's rewards, costs and "
                "observations, try a lower algo.lr, or raise max_nonfinite_updates"
            )

    # ---------------------------------------------------------- checkpoint
    def state_dict(self) -> dict[str, Any]:
        state: dict[str, Any] = {
            "config": OmegaConf.to_container(self.cfg, resolve=True),
            "frames": self.tracker.frames,
            "total_cost": self.tracker.total_cost,
            "training_safety": self.training_safety.state_dict(),
            "updates": self.updates,
            "skipped_updates": self.skipped_updates,
            # flushes the logger; on resume wandb continues the same run from it
            "logger": None
            if self.logger is None
            else {"backend": str(self.cfg.logger.backend), "state": self.logger.state_dict()},
            "epoch": self.epoch,
            "elapsed": self.elapsed,
            "epoch_progress": self._epoch_progress(),
            "rng": {
                "torch": torch.get_rng_state(),
                "numpy": numpy_rng_state(),  # plain data: read with weights_only=True
                "python": random.getstate(),
            },
        }
        state["learner"] = self.learner_state()
        return state

    def _epoch_progress(self) -> dict[str, Any]:
        """What the epoch in progress has gathered so far (empty at an epoch's end)."""
        clock = self._epoch_clock
        means = self.loss_means
        return {
            "start_frames": self.epoch_start_frames,
            "start_updates": self.epoch_start_updates,
            "seconds": self.epoch_seconds + (time.time() - clock if clock is not None else 0.0),
            "returns": list(self.tracker.returns),
            "costs": list(self.tracker.costs),
            "lengths": list(self.tracker.lengths),
            "failures": self.tracker.failures,
            "skipped_updates": self.epoch_skipped_updates,
            "loss_sums": None
            if means.total is None
            else {key: float(means.total[key]) for key in means.keys},
            "loss_count": means.count,
        }

    def _load_epoch_progress(self, progress: dict[str, Any] | None) -> None:
        if not progress:  # checkpoints from before: the epoch restarts its statistics
            self.epoch_start_frames, self.epoch_start_updates = self.tracker.frames, self.updates
            return
        self.epoch_start_frames = int(progress["start_frames"])
        self.epoch_start_updates = int(progress["start_updates"])
        self.epoch_seconds = float(progress["seconds"])
        self.tracker.returns = list(progress["returns"])
        self.tracker.costs = list(progress["costs"])
        self.tracker.lengths = list(progress["lengths"])
        self.tracker.failures = int(progress["failures"])
        self.epoch_skipped_updates = int(progress["skipped_updates"])
        sums = progress.get("loss_sums")
        if sums is not None and set(sums) == set(self.loss_means.keys):
            self.loss_means.total = TensorDict(
                {k: torch.tensor(v, dtype=torch.float64) for k, v in sums.items()}
            )
            self.loss_means.count = int(progress["loss_count"])

    def save(self) -> Path:
        """Write ``checkpoints/last.pt`` atomically (then :meth:`after_save`)."""
        state = self.state_dict()
        save_checkpoint(self.checkpoint_path, state)
        self._checkpoint_frames = self.tracker.frames
        self.after_save(state)
        return self.checkpoint_path

    def after_save(self, state: dict[str, Any]) -> None:
        """Called once the checkpoint holding ``state`` is in place (e.g. to remove files
        that only older checkpoints needed)."""

    def _load_state(self, state: dict[str, Any]) -> None:
        self.tracker = EpisodeTracker(
            frames=int(state["frames"]),
            total_cost=float(state["total_cost"]),
            goals=has_goals(self.cfg.env.name),
        )
        self.updates = int(state["updates"])
        self.skipped_updates = int(state.get("skipped_updates", 0))
        self.epoch = int(state["epoch"])
        self.elapsed = float(state.get("elapsed", 0.0))
        self._load_epoch_progress(state.get("epoch_progress"))
        self.training_safety = self._load_training_safety(state.get("training_safety"))

    def _load_training_safety(self, saved: dict[str, Any] | None) -> TrainingSafety:
        """The checkpoint's training-safety counts; a checkpoint from before them counts
        the epochs ``progress.csv`` logged up to it again (none: from this epoch on)."""
        if saved is not None:
            return TrainingSafety.from_state(saved)
        path = self.run_dir / "progress.csv"
        columns = read_progress(path) if path.is_file() else {}
        kept = [i for i, epoch in enumerate(columns.get("epoch", ())) if epoch <= self.epoch]
        try:
            return training_safety(
                {key: [values[i] for i in kept] for key, values in columns.items()},
                float(self.cfg.cost_limit),
            )
        except ValueError:  # no progress.csv, or one without the cost columns
            return TrainingSafety(float(self.cfg.cost_limit))

    @staticmethod
    def _restore_rng(rng: dict[str, Any], path: Path | None = None) -> None:
        try:
            torch.set_rng_state(rng["torch"])
            set_numpy_rng_state(rng["numpy"])
            random.setstate(rng["python"])
        except (KeyError, TypeError, ValueError, RuntimeError) as err:
            raise ConfigError(
                f"checkpoint {path}: its 'rng' entry is not the RNG states train.py saves "
                f"({first_line(err)[:200]}); pass a checkpoint written by train.py"
            ) from None

    def close(self) -> None:
        """Release envs, flush the logger and give up the run directory's lock."""
        for env in (self.env, self.eval_env):
            if env is not None and not env.is_closed:
                env.close()
        experiment = getattr(self.logger, "experiment", None)
        if hasattr(experiment, "finish"):  # wandb
            experiment.finish()
        for handle in getattr(experiment, "files", {}).values():  # TorchRL's CSV logger
            handle.close()
        if hasattr(experiment, "close") and not hasattr(experiment, "files"):  # tensorboard
            experiment.close()
        if self.lock is not None:
            self.lock.release()


class RandomPolicyTrainer(Trainer):
    """The paper's "Random Policy" row: uniform random actions, nothing learned.

    Training and test episodes are logged like any other run, so the same tooling
    evaluates it.
    """
