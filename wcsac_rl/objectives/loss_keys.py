"""Keys that follow a loss's ``set_keys``: what a helper built by ``for_loss`` reads.

``NStepCost.for_loss(loss)``, ``StartStateBuffer.for_loss(loss)`` and
``EpisodeCostWindow.for_loss(loss)`` write (or read) entries under keys of the loss.
TorchRL's losses forward ``set_keys`` to their value estimator; these helpers instead
read the key from ``loss.tensor_keys`` (the dataclass ``set_keys`` changes in place)
each time they use it, so a ``loss.set_keys(cost=...)`` made after them is followed.
A helper built with its own keys keeps them.
"""

from __future__ import annotations

from typing import Any

__all__ = ["LossKey", "follow_loss_keys"]


class LossKey:
    """A key attribute: the object's own, or, once :func:`follow_loss_keys` bound it to a
    loss, that loss's current ``tensor_keys.<field>``."""

    def __init__(self, field: str) -> None:
        self.field = field

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, obj: Any, objtype: type | None = None) -> Any:
        if obj is None:
            return self
        loss_keys = obj.__dict__.get("_loss_keys")
        if loss_keys is not None:
            return getattr(loss_keys, self.field)
        return obj.__dict__["_own_keys"][self.name]

    def __set__(self, obj: Any, value: Any) -> None:
        if obj.__dict__.get("_loss_keys") is not None:
            raise AttributeError(
                f"{type(obj).__name__}.{self.name} follows the loss it was built for; "
                f"change it with loss.set_keys({self.field}=...)"
            )
        obj.__dict__.setdefault("_own_keys", {})[self.name] = value


def follow_loss_keys(obj: Any, loss: Any) -> Any:
    """Make ``obj``'s :class:`LossKey` attributes read ``loss.tensor_keys``; returns ``obj``."""
    obj.__dict__["_loss_keys"] = loss.tensor_keys
    return obj
