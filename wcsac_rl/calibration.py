"""Safety-critic calibration of a trained run: ``python -m wcsac_rl.calibration RUN_DIR``.

Compares the final checkpoint's safety critic (Q^c, Γ_α, √V^c) with the realised
discounted cost-to-go of deterministic test episodes, seeded as ``wcsac_rl.evaluate``'s
(:mod:`wcsac_rl.evaluation.run_calibration`); prints a table and writes
``calibration.json`` beside the run (not over an existing one without ``--force``).
Errors print one ``error:`` line and exit with code 1.

Examples::

    python -m wcsac_rl.calibration outputs/2026-11-22/10-00-00_wcsac_0.5_static_seed0
    python -m wcsac_rl.calibration RUN_DIR --episodes 100 --force
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from wcsac_rl.evaluate import add_episode_arguments, add_process_arguments, check_episode_arguments
from wcsac_rl.evaluation.defaults import DEFAULT_SEED_OFFSET

__all__ = ["DEFAULT_CALIBRATION_EPISODES", "format_table", "main", "parse_args"]

DEFAULT_CALIBRATION_EPISODES = 30


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line of ``python -m wcsac_rl.calibration``."""
    parser = argparse.ArgumentParser(
        prog="python -m wcsac_rl.calibration",
        description=(
            "Compare a trained run's safety critic (Q^c, Γ_α, √V^c) with the costs its "
            "policy realises on deterministic test episodes; print a table and save "
            "calibration.json beside the run."
        ),
    )
    parser.add_argument("run_dir", type=Path, help="a run directory (with checkpoints/last.pt)")
    add_episode_arguments(
        parser,
        episodes=DEFAULT_CALIBRATION_EPISODES,
        episodes_help=f"test episodes (default {DEFAULT_CALIBRATION_EPISODES})",
        seed_help="seed offset of the test episodes: the env is seeded training seed + SEED "
        f"(default {DEFAULT_SEED_OFFSET}, as python -m wcsac_rl.evaluate)",
    )
    parser.add_argument("--force", action="store_true", help="overwrite calibration.json")
    add_process_arguments(parser)
    args = parser.parse_args(argv)
    check_episode_arguments(parser, args)
    return args


def _number(value: float | None) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    return f"{value:.3f}"


def format_table(result: dict[str, Any]) -> str:
    """A few readable lines from the result of
    :func:`~wcsac_rl.evaluation.run_calibration.calibrate_run`."""
    m = result["metrics"]
    alpha = result["risk_level"]
    iqn = result.get("safety_critic") == "iqn"
    rows = [
        ("start state s0", "predicted", "realised", ""),
        ("  mean Q^c / cost-to-go", m["start_cost_value"], m["start_realised_cost_to_go"], ""),
        (
            f"  Γ_α / CVaR_α (α = {alpha:g})",
            m["start_cvar"],
            m["start_realised_cvar"],
            f"ratio {_number(m['start_cvar_ratio'])}",
        ),
        (
            "  mixture CVaR_α over s0",
            m["start_tail_cvar"],
            m["start_realised_cvar"],
            f"ratio {_number(m['start_tail_ratio'])}",
        ),
        (
            "  std of quantiles / spread" if iqn else "  √V^c / spread",
            m["start_std"],
            m["realised_spread"],
            "",
        ),
        ("all visited states", "", "", ""),
        ("  mean Q^c / cost-to-go", m["mean_cost_value"], m["mean_realised_cost_to_go"], ""),
        ("  correlation", m["correlation"], "", ""),
        ("  share with Q^c < 0", m["negative_share"], "", ""),
        ("episodic cost (undiscounted)", "", "", ""),
        ("  mean", "", m["episode_cost"], ""),
        (f"  CVaR_α (α = {alpha:g})", "", m["episode_cvar"], ""),
    ]
    lines = [
        f"{result['label']}{' (IQN safety critic)' if iqn else ''} on {result['env']}, "
        f"seed {result['seed']}, "
        f"{result['trained_frames']} frames: {result['episodes']} deterministic episodes "
        f"({result['episodes_at_time_limit']} cut at {result['max_episode_steps']} steps), "
        f"γ_c = {result['cost_gamma']:g}, κ-loss threshold {result['cost_threshold']:.4g}"
    ]
    for name, predicted, realised, note in rows:
        cells = [c if isinstance(c, str) else _number(c) for c in (predicted, realised)]
        lines.append(f"{name:<32}{cells[0]:>10}{cells[1]:>10}  {note}".rstrip())
    return "\n".join([*lines, *training_lines(result)])


def _count(value: float | None) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    return str(int(value))


def training_lines(result: dict[str, Any]) -> list[str]:
    """The table's part on the training episodes: per epoch whose training episodes
    cost more than ``d`` (and the last epoch), the critic's reading when they were
    collected against their realised discounted cost-to-go, at their start states and
    over their steps (``result["training_episodes"]``, the run's ``train_calib/*``
    columns); one line when the run did not log them."""
    epochs = result.get("training_episodes") or []
    if not epochs:
        return ["training episodes: not logged (train_calib/* columns: a run from before them)"]
    over = [e for e in epochs if (e.get("over_episodes") or 0) > 0]
    shown = [*over, epochs[-1]] if not over or over[-1] is not epochs[-1] else over
    d = result.get("cost_limit", math.nan)
    lines = [
        f"training episodes, read when collected ({len(over)} of {len(epochs)} epochs had "
        f"episodes over d = {d:g}; the last epoch too)",
        f"{'  frames':<10}{'episodes':>9}{'over d':>7}{'Γ(s0)':>9}{'CVaR G0':>9}{'ratio':>8}"
        f"{'Γ over d':>10}{'G over d':>10}{'ratio':>8}",
    ]
    for e in shown:
        lines.append(
            f"  {_count(e['frames']):<8}{_count(e['episodes']):>9}{_count(e['over_episodes']):>7}"
            f"{_number(e['start_cvar']):>9}{_number(e['start_realised_cvar']):>9}"
            f"{_number(e['start_ratio']):>8}{_number(e['over_cvar']):>10}"
            f"{_number(e['over_cost_to_go']):>10}{_number(e['over_ratio']):>8}"
        )
    lines.append(
        "  (ratio < 1 over d: the critic under-read the route as it was taken; ≈ 1: it "
        "anticipated; > 1: it over-read)"
    )
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    """Calibrate one run; return the exit code (1 on an error a user can cause)."""
    args = parse_args(argv)
    import torch

    from wcsac_rl.evaluation.evaluator import _progress
    from wcsac_rl.evaluation.run_calibration import calibrate_run
    from wcsac_rl.training.config import ConfigError

    torch.set_num_threads(args.threads)
    progress: list = []  # (bar, callback), made at the first episode: none before an error

    def on_episode(episode) -> None:
        if not progress:
            progress.extend(_progress(args.episodes, "calibration", not args.no_progress))
        progress[1](episode)

    try:
        path, result = calibrate_run(
            args.run_dir,
            episodes=args.episodes,
            seed_offset=args.seed,
            force=args.force,
            max_episode_steps=args.max_episode_steps,
            on_episode=on_episode,
            trust_env_code=args.trust_env_code,
        )
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        return 1
    finally:
        if progress:
            progress[0].close()
    print(format_table(result))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
