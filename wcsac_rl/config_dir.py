"""Where the Hydra config groups are: ``conf/`` of a checkout, or the copy an install ships.

The single source is ``conf/`` at the top of the repository. A regular (non-editable)
``pip install`` ships it inside the package as ``wcsac_rl/conf`` (``setup.py`` maps the
package ``wcsac_rl.conf`` to ``conf/``), so ``wcsac-train`` composes the same configs
from any directory. This module imports nothing heavy: ``wcsac-train --help`` reads it.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["CONF_DIR", "find_conf_dir"]


def find_conf_dir() -> Path:
    """The installed copy (``<package>/conf``) if there is one, else the checkout's
    ``conf/`` beside the package (which is also what an editable install sees)."""
    package = Path(__file__).resolve().parent
    shipped = package / "conf"
    if (shipped / "config.yaml").is_file():
        return shipped
    return package.parent / "conf"


CONF_DIR = find_conf_dir()
"""The directory ``wcsac-train`` / ``train.py`` compose their config from."""
