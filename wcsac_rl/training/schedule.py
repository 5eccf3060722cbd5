"""A run's frame schedule in whole collector batches, and the lines that say so.

An epoch or a run ends only at a batch boundary: ``total_frames`` and ``epoch_frames``
are rounded up to whole batches (one line each), and a budget at or under the random
warm-up is one ``warning:`` line (docs/training.md, "Configuration"). Every entry point
trains through :class:`~wcsac_rl.training.trainer.Trainer`, which reads the schedule
from here.
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
