"""The option schema Hydra composes ``algo`` from: registered with Hydra's ConfigStore.

``conf/algo/wcsac.yaml`` (and so ``sac_lag``, ``wcsac_paper``, ``sac_lag_paper``) starts
its defaults list with ``/schema/safety_options``: the defaults of every field of
:class:`~wcsac_rl.options.SafetyOptions`, stored here under the ``schema``
group (package ``algo``), as TorchRL registers its ``SACLossConfig``: the paper's WCSAC
(:data:`~wcsac_rl.options.PAPER_OPTIONS`). The YAML files then set only the values that
differ, with their comments.

The node holds the dataclass's values, not its types: OmegaConf would otherwise refuse
a mistyped value (``algo.variance=maybe``) while Hydra composes, in its own multi-line
message and before the kit's validator could name the key and what it may be in one
line (``algo.variance must be true or false, got 'maybe'``); and a typed node is closed,
while ``algo`` also holds the SAC family's options (``off_policy.yaml``). The types and
ranges are checked by :func:`~wcsac_rl.options.read_options`, from the same
dataclass.

It also registers the resolver ``${wcsac_rl.config_groups:}``: the groups a user picks
(:func:`~wcsac_rl.recipes.config_groups`), which ``conf/config.yaml``'s help template
lists in place of Hydra's list of every group.

Importing this module registers the schema (once); ``import wcsac_rl`` does it, so
every way of composing ``conf/`` (``wcsac-train``, ``compose_config``, Hydra's own
``compose``) finds it. It imports no torch.
"""

from __future__ import annotations

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from wcsac_rl.config_dir import CONF_DIR
from wcsac_rl.options import SafetyOptions, config_defaults
from wcsac_rl.recipes import config_groups

__all__ = ["SCHEMA_GROUP", "register_configs"]

SCHEMA_GROUP = "schema"
"""The ConfigStore group of the nodes below (``/schema/<name>`` in a defaults list)."""


def register_configs() -> None:
    """Store :class:`SafetyOptions`' defaults as ``schema/safety_options`` (package
    ``algo``) and register the help template's resolver."""
    store = ConfigStore.instance()
    store.store(
        group=SCHEMA_GROUP,
        name="safety_options",
        node=config_defaults(SafetyOptions),
        package="algo",
    )
    OmegaConf.register_new_resolver(
        "wcsac_rl.config_groups", lambda: config_groups(CONF_DIR), replace=True
    )


register_configs()
