"""A run's frame schedule in whole collector batches, and the lines that say so.

The collector hands over ``algo.collector.frames_per_batch`` frames at a time, and an
epoch or a run can only end at a batch boundary. Every entry point (``train.py``,
:func:`~wcsac_rl.train.run_training`, the experiments, the calibration runs) trains
through :class:`~wcsac_rl.training.trainer.Trainer`, which reads the schedule from here:

* ``total_frames`` that is not a whole number of batches is rounded up (TorchRL's
  collector does), said in one line;
* ``epoch_frames`` likewise: every epoch is the same whole number of batches (without
  the rounding, ``epoch_frames=1000`` over batches of 400 gave epochs ending at 1 200,
  2 000, 3 200, 4 000 frames), said in one line;
* a budget at or under the random warm-up (``algo.collector.init_random_frames``, whole
  batches too) collects no frame with the policy and trains it, if at all, after the
  last batch: one ``warning:`` line naming both numbers.
"""

from __future__ import annotations

import math

from omegaconf import DictConfig

__all__ = ["epoch_frames", "schedule_notes", "whole_batches"]


def whole_batches(frames: int, batch: int) -> int:
    """``frames`` rounded up to a whole number of collector batches of ``batch`` frames."""
    return math.ceil(int(frames) / int(batch)) * int(batch)


def epoch_frames(cfg: DictConfig) -> int:
    """The frames of one epoch: ``epoch_frames`` in whole collector batches."""
    return whole_batches(int(cfg.epoch_frames), int(cfg.algo.collector.frames_per_batch))


def schedule_notes(
    cfg: DictConfig, *, frames_done: int = 0, init_random_frames: int = 0
) -> list[str]:
    """The lines a run prints before it collects (none when it has nothing left to do).

    Args:
        cfg: the run's config.
        frames_done: frames an earlier session of the run collected (a resume).
        init_random_frames: the trainer's random warm-up (0: none, as on-policy runs).
    """
    batch = int(cfg.algo.collector.frames_per_batch)
    total = int(cfg.total_frames)
    remaining = max(0, total - int(frames_done))
    if remaining == 0:
        return []
    notes = []
    collected = int(frames_done) + whole_batches(remaining, batch)
    whole = f"(whole collector batches of {batch} frames)"
    if remaining % batch:
        notes.append(f"total_frames={total} is rounded up to {collected} {whole}")
    if int(cfg.epoch_frames) % batch:
        notes.append(
            f"epoch_frames={int(cfg.epoch_frames)} is rounded up to {epoch_frames(cfg)} {whole}"
        )
    if init_random_frames > 0 and collected <= whole_batches(init_random_frames, batch):
        notes.append(
            f"warning: total_frames={total} is at or under algo.collector.init_random_frames="
            f"{int(init_random_frames)} (the random warm-up): no frame is collected by the "
            "policy, which trains after the last batch if at all; raise total_frames or "
            "lower algo.collector.init_random_frames"
        )
    return notes
