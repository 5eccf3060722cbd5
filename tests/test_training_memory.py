"""Nothing per gradient step outlives its collected batch.

Keeping every update's loss outputs until the end of the epoch (7 500 small
TensorDicts per epoch at the paper's settings) fragmented the heap between the
update's activations: 7.9 GB RSS for SAC-Lag after 30 k frames. The epoch means are
now summed batch by batch (``LossMeans``) and the episode statistics kept as numbers.
``benchmarks/bench_memory.py`` measures the RSS itself.
"""

from __future__ import annotations

import gc
import weakref

import torch
from _training_helpers import compose_config
from tensordict import TensorDict

from wcsac_rl.training import make_trainer
from wcsac_rl.training.progress import EpisodeTracker, LossMeans


def test_update_outputs_do_not_outlive_their_batch(tmp_path):
    trainer = make_trainer(
        compose_config("env=tiny", "algo=sac_lag", "total_frames=1200"), tmp_path / "r"
    )
    alive_at_epoch_end = []
    refs: list[weakref.ref] = []
    real_update, real_row = trainer.update, trainer._epoch_row

    def update(batch):
        out = real_update(batch)
        if out is not None:
            refs.append(weakref.ref(out))
        return out

    def epoch_row(*args, **kwargs):
        gc.collect()
        alive_at_epoch_end.append(sum(ref() is not None for ref in refs))
        return real_row(*args, **kwargs)

    trainer.update, trainer._epoch_row = update, epoch_row
    try:
        trainer.run()
    finally:
        trainer.close()
    assert len(refs) == 300  # 50 updates after each of the 6 batches of 200 frames
    assert alive_at_epoch_end == [0, 0, 0]


def test_loss_means_are_the_means_of_what_was_added():
    means = LossMeans(["a", "b"])
    assert all(v != v for v in means.means().values())  # NaN before anything is added
    outputs = [
        TensorDict({"a": torch.tensor(float(i)), "b": torch.tensor(2.0), "c": torch.tensor(9.0)})
        for i in range(4)
    ]
    means.add(outputs[:3])
    means.add(outputs[3:])
    assert means.means() == {"loss/a": 1.5, "loss/b": 2.0}
    means.reset()
    assert means.count == 0


def test_episode_tracker_keeps_numbers_not_tensors():
    tracker = EpisodeTracker()
    done = torch.tensor([[False], [True]])
    batch = TensorDict(
        {
            "next": {
                "done": done,
                "episode_reward": torch.tensor([[1.0], [2.5]]),
                "episode_cost": torch.tensor([[0.0], [3.0]]),
                "step_count": torch.tensor([[4], [7]]),
                "cost": torch.tensor([[0.0], [1.0]]),
            }
        },
        [2],
    )
    tracker.add(batch)
    assert tracker.returns == [2.5] and tracker.costs == [3.0] and tracker.lengths == [7]
    metrics = tracker.epoch_metrics()
    assert metrics["train/episodes"] == 1 and metrics["train/episode_length"] == 7.0
