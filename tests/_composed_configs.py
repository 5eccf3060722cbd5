"""Every algorithm × env, row and experiment of ``conf/`` as it composes, flattened to
``{"algo.kappa_init": 0.69..., ...}`` (not collected: no ``test_`` prefix).

``python tests/_composed_configs.py`` writes ``tests/data/composed_configs.json``; it
was run once on the layout before the recipes moved into one file per algorithm
(eb55fde), and ``tests/test_config_layout.py`` composes the same combinations today
and compares them key by key.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

CONF = Path(__file__).resolve().parents[1] / "conf"
FIXTURE = Path(__file__).parent / "data" / "composed_configs.json"

ALGOS = ("wcsac", "wcsac_paper", "sac", "sac_lag", "sac_lag_paper", "cpo", "random")
# every selectable algorithm: the recorded ones and those added after the recording
ALL_ALGOS = (*ALGOS, "cal")
NEW_ROWS = ("cal",)  # rows added after the recording (their algorithm was not recorded)
ENVS = ("static", "dynamic", "tiny", "point_goal1", "point_goal2", "gymnasium")
GYMNASIUM_ID = "env.id=MyTask-v0"  # (env=gymnasium needs an id; none is imported here)


def env_overrides(env: str) -> tuple[str, ...]:
    return (f"env={env}", GYMNASIUM_ID) if env == "gymnasium" else (f"env={env}",)


def _sweep_rows(experiment: str) -> list[str]:
    """The ``+row`` values an experiment file sweeps (its own or its parent's)."""
    node = yaml.safe_load((CONF / "experiment" / f"{experiment}.yaml").read_text())
    rows = (((node.get("hydra") or {}).get("sweeper") or {}).get("params") or {}).get("+row")
    if rows is not None:
        return str(rows).split(",")
    for entry in node.get("defaults", []):
        if isinstance(entry, str) and entry != "_self_":
            return _sweep_rows(entry)
    return []


def combinations() -> list[tuple[str, ...]]:
    """Every override list the fixture records: each algorithm on each env, each row on
    each env, and each experiment alone and with each row it sweeps."""
    combos = [(f"algo={a}", *env_overrides(e)) for a in ALGOS for e in ENVS]
    rows = sorted(p.stem for p in (CONF / "row").glob("*.yaml") if p.stem not in NEW_ROWS)
    combos += [(f"+row={r}", *env_overrides(e)) for r in rows for e in ENVS]
    for path in sorted((CONF / "experiment").glob("*.yaml")):
        combos.append((f"experiment={path.stem}",))
        swept = [r for r in _sweep_rows(path.stem) if r not in NEW_ROWS]
        combos += [(f"experiment={path.stem}", f"+row={r}") for r in swept]
    return combos


def leaves(node: Any, prefix: str = "") -> dict[str, Any]:
    """``{"a.b": leaf}`` for every leaf of a nested dict (an empty dict is a leaf)."""
    if isinstance(node, dict) and node:
        out: dict[str, Any] = {}
        for key, value in node.items():
            out.update(leaves(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: node}


def compose_leaves(overrides: tuple[str, ...]) -> dict[str, Any]:
    """The job config ``train.py <overrides>`` composes (Hydra's own node left out),
    every interpolation resolved, flattened."""
    import wcsac_rl  # noqa: F401  (registers the option schema)

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("config", overrides=list(overrides), return_hydra_config=False)
    return leaves(OmegaConf.to_container(cfg, resolve=True))


def key(overrides: tuple[str, ...]) -> str:
    return " ".join(overrides)


def record() -> dict[str, dict[str, Any]]:
    return {key(c): compose_leaves(c) for c in combinations()}


if __name__ == "__main__":
    FIXTURE.parent.mkdir(exist_ok=True)
    FIXTURE.write_text(json.dumps(record(), indent=1, sort_keys=True) + "\n")
    print(f"wrote {FIXTURE} ({len(combinations())} combinations)", file=sys.stderr)
