"""What the kit's losses add to TorchRL's :class:`~torchrl.objectives.LossModule`: a key
name or a state dict that does not fit the loss is one line naming it."""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from dataclasses import fields
from typing import Any

import torch

__all__ = ["CheckedLoss"]


class CheckedLoss:
    """A mixin before ``LossModule`` (or a subclass) in a loss's bases: ``set_keys`` with
    a name the loss does not read, and ``load_state_dict`` with a tensor of another shape
    than the loss's own (an ensemble of 4 critics into a loss of 2), each raise one
    ``ValueError`` line naming it; nothing is changed."""

    def set_keys(self, **kwargs: Any) -> Any:
        accepted = [f.name for f in fields(self._AcceptedKeys)]
        for name in kwargs:
            if name not in accepted:
                close = difflib.get_close_matches(name, accepted, n=1)
                hint = f"; did you mean {close[0]!r}?" if close else ""
                raise ValueError(
                    f"{type(self).__name__}.set_keys: {name!r} is not a key of the loss "
                    f"(its keys: {', '.join(accepted)}){hint}"
                )
        return super().set_keys(**kwargs)

    def load_state_dict(self, state_dict: Mapping[str, Any], *args: Any, **kwargs: Any) -> Any:
        own = self.state_dict()
        for key, value in state_dict.items():
            mine = own.get(key)
            if isinstance(value, torch.Tensor) and isinstance(mine, torch.Tensor):
                if value.shape != mine.shape:
                    raise ValueError(
                        f"{type(self).__name__}.load_state_dict: {key} has shape "
                        f"{list(value.shape)} in the state dict, {list(mine.shape)} in this "
                        "loss; build the loss as the one that saved it (e.g. the same "
                        "num_safety_nets and network widths)"
                    )
        return super().load_state_dict(state_dict, *args, **kwargs)
