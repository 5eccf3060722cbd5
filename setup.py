"""Packaging beyond ``pyproject.toml``: ship the Hydra configs inside the package.

``conf/`` stays at the top of the repository (the one copy to edit); a regular
(non-editable) install maps it to the package ``wcsac_rl.conf`` (each config group a
sub-package holding its ``*.yaml``), so ``wcsac-train`` finds its configs wherever it
runs (:mod:`wcsac_rl.config_dir`). Everything else is in ``pyproject.toml``.
"""

from pathlib import Path

from setuptools import find_packages, setup

CONF = Path(__file__).resolve().parent / "conf"
CONF_PACKAGES = [
    "wcsac_rl.conf",
    *(
        ".".join(("wcsac_rl.conf", *d.relative_to(CONF).parts))
        for d in sorted(CONF.rglob("*"))
        if d.is_dir()
    ),
]

setup(
    packages=[*find_packages(include=["wcsac_rl*"]), *CONF_PACKAGES],
    package_dir={"wcsac_rl.conf": "conf"},
    package_data={package: ["*.yaml"] for package in CONF_PACKAGES},
)
