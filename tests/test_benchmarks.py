"""Every benchmark script runs, at tiny sizes, and reports what it measures.

Each ``benchmarks/bench_*.py`` is run as ``make bench`` runs it, and so is
``benchmarks/profile_update.py`` (``python
benchmarks/<script>``, a fresh process; this checkout's package first on the path)
with options that make it small: tiny networks and batches, one round of one update,
the tiny env. Its ``--json`` output is then read: every row the script promises is
there, every figure finite and positive, and the figures that follow from the
schedule are what it fixes (updates per frame, buffer rows). A benchmark that breaks
(as ``bench_update.py`` did when the loss's defaults began to read n-step entries)
fails here; a new script in ``benchmarks/`` without an entry in ``SMOKE_ARGS`` fails too.

Nothing here is a timing claim: the rates only have to be measured at all.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

from wcsac_rl.objectives import loss_parts
from wcsac_rl.options import SafetyOptions
from wcsac_rl.training.builders import safety_critic_kwargs

ROOT = Path(__file__).resolve().parents[1]
BENCHMARKS = ROOT / "benchmarks"

TINY_UPDATE = ["--batch", "8", "--width", "16", "--rounds", "1", "--updates", "1"]
SMOKE_ARGS = {
    "bench_envs.py": ["--steps", "40", "--envs", "tiny", "static"],
    "bench_ensemble.py": [*TINY_UPDATE, "--warmup", "1"],
    "bench_update.py": [
        *TINY_UPDATE,
        *("--warmup", "1", "--peak-seconds", "0.01"),
        *("--env", "tiny", "--env-steps", "40", "--loop-frames", "1200"),
    ],
    "bench_memory.py": [
        *("--algos", "wcsac", "wcsac_paper", "--env", "tiny", "--frames", "800"),
        "--override",
        "algo.collector.init_random_frames=400",
        "algo.network.width=16",
        "algo.batch_size=8",
        "algo.buffer_size=1500",  # --fill fills it from a 1 000-step rollout
    ],
    "bench_help.py": ["--repeats", "1"],
    "bench_trainer_update.py": [
        *("--env", "tiny", "--rounds", "2", "--updates", "2", "--warmup", "1", "--fill", "400"),
        *("--override", "algo.network.width=16", "algo.batch_size=8"),
    ],
    "gpu_check.py": [
        *("--device", "cpu", "--env", "tiny", "--frames", "800", "--epoch-frames", "400"),
        *("--no-tests", "--modes", "eager", "--override", "algo.network.width=16"),
        *("algo.batch_size=8", "algo.collector.init_random_frames=200"),
    ],
    "profile_update.py": [
        *("--batch", "8", "--width", "16", "--updates", "2", "--warmup", "1", "--repeats", "1"),
        *("--ablation", "1"),
    ],
}
"""Tiny options for each script of ``benchmarks/`` (every one with a ``__main__`` needs one)."""


def run_benchmark(script: str, tmp_path: Path) -> object:
    out = tmp_path / f"{script}.json"
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
        "OMP_NUM_THREADS": "1",
    }
    proc = subprocess.run(
        [sys.executable, str(BENCHMARKS / script), *SMOKE_ARGS[script], "--json", str(out)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, f"{script} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return json.loads(out.read_text())


def assert_positive(row: dict, *keys: str) -> None:
    for key in keys:
        value = row[key]
        assert isinstance(value, int | float) and math.isfinite(value) and value > 0, (key, row)


def test_every_benchmark_script_has_smoke_options():
    scripts = [p.name for p in BENCHMARKS.glob("*.py") if "__main__" in p.read_text()]
    assert sorted(scripts) == sorted(SMOKE_ARGS)
    assert {p.name for p in BENCHMARKS.glob("bench_*.py")} <= set(scripts)  # make bench's


def test_bench_envs_runs(tmp_path):
    rows = run_benchmark("bench_envs.py", tmp_path)
    assert [row["env"] for row in rows] == ["tiny", "static"]
    for row in rows:
        assert_positive(row, "raw_steps_per_s", "torchrl_steps_per_s", "batched4_frames_per_s")


def test_bench_help_times_every_console_script_without_torch(tmp_path):
    """Each console script of pyproject.toml answers --help (timed, not asserted here: the
    figure is docs/performance.md's) without importing torch, torchrl or matplotlib."""
    rows = run_benchmark("bench_help.py", tmp_path)
    text = (ROOT / "pyproject.toml").read_text().split("[project.scripts]")[1].split("\n[")[0]
    scripts = [line.split("=")[0].strip() for line in text.splitlines() if "=" in line]
    assert [row["script"] for row in rows] == scripts and len(scripts) >= 4
    for row in rows:
        assert_positive(row, "min_s", "median_s", "help_lines")
        assert row["heavy_modules"] == "", row


def test_bench_trainer_update_times_the_trainers_own_update(tmp_path):
    rows = run_benchmark("bench_trainer_update.py", tmp_path)
    assert [row["mode"] for row in rows] == ["eager"]
    assert rows[0]["rounds"] == 2
    assert_positive(rows[0], "updates_per_s")


def test_bench_trainer_update_compares_two_checkouts_round_by_round(tmp_path):
    """``--against``: two worker processes (here both on this checkout), their rounds
    interleaved; each side's rate and the rounds' ratios."""
    out = tmp_path / "against.json"
    args = [*SMOKE_ARGS["bench_trainer_update.py"], "--against", str(ROOT), "--json", str(out)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [sys.executable, str(BENCHMARKS / "bench_trainer_update.py"), *args],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    *sides, ratio = json.loads(out.read_text())
    assert [row["side"] for row in sides] == ["this", "against"]
    for row in sides:
        assert row["checkout"] == str(ROOT) and row["rounds"] == 2
        assert_positive(row, "updates_per_s")
    assert len(ratio["round_ratios"]) == 2 and len(ratio["pair_ratios"]) == 1
    assert ratio["ratio_this_over_against"] == ratio["pair_ratios"][0] > 0


def test_bench_update_runs_at_every_option_set(tmp_path):
    result = run_benchmark("bench_update.py", tmp_path)
    assert result["sizes"] == {"batch": 8, "width": 16, "obs": 44, "act": 2}
    assert result["threads"] == 1
    assert len(result["matmul_peak_gflops"]) == 3
    assert all(math.isfinite(v) and v > 0 for v in result["matmul_peak_gflops"].values())
    rows = {row["name"]: row for row in result["updates"]}
    expected = {"sac", "sac_polyak", "sac_torchrl_nets", "plain_wcsac_paper"}
    expected.update({"wcsac_kit_module_calls", "wcsac_kit_signal_every10"})
    for options in ("kit", "gaussian", "paper"):
        for suffix in ("", "_general", "_torchrl_nets"):
            expected.add(f"wcsac_{options}{suffix}")
    assert set(rows) == expected
    for name, row in rows.items():
        assert_positive(row, "updates_per_s", "vs_sac", "gflop_per_update", "gflop_per_s")
        assert_positive(row, "of_peak")
        baseline = rows[row["baseline"]]
        assert row["vs_sac"] == pytest.approx(row["updates_per_s"] / baseline["updates_per_s"])
        if name.startswith("wcsac_"):
            assert row["options"] == name.split("_")[1]
    flops = {name: row["gflop_per_update"] for name, row in rows.items()}
    # the same networks and batch: WCSAC's four critics do more matrix work than SAC's
    # two, and the Gaussian set's extra evaluations (n-step targets, start states) more still
    assert flops["sac"] == flops["sac_polyak"] < flops["wcsac_paper"] < flops["wcsac_gaussian"]
    # the fused and the general path multiply the same matrices, but for the n-step
    # targets, where the fused ensemble keeps its one product over every member at s'
    assert flops["wcsac_paper_general"] == pytest.approx(flops["wcsac_paper"])
    assert flops["wcsac_gaussian_general"] < flops["wcsac_gaussian"]
    # the kit's IQN critic is not in the fused ensemble: both paths multiply the same
    # matrices; with a user's Gaussian critic the kit's options cost what the Gaussian set's
    # do (κ's second signal, the episodes' CVaR, is no matrix work)
    assert flops["wcsac_kit_general"] == pytest.approx(flops["wcsac_kit"])
    # reading the critics from their parameters multiplies the same matrices
    assert flops["wcsac_kit_module_calls"] == flops["wcsac_kit"]
    # κ's start-state tail read once in 10 updates: that evaluation's work in 1 of 10
    assert flops["wcsac_kit_signal_every10"] < flops["wcsac_kit"]
    assert flops["wcsac_kit_torchrl_nets"] == pytest.approx(flops["wcsac_gaussian_torchrl_nets"])

    loop = result["loop"]
    env_rows = [row for row in loop if "options" not in row]
    assert len(env_rows) == 3
    for row in env_rows:
        assert_positive(row, "value")
    runs = {row["options"]: row for row in loop if "options" in row}
    assert set(runs) == {"kit", "gaussian", "paper"}
    for row in runs.values():
        assert_positive(row, "fps", "ups", "of_ceiling")
        # UTD 0.25 (100 updates per 400-frame batch): over a whole epoch, updates per frame
        assert row["ups"] / row["fps"] == pytest.approx(0.25)


def test_bench_ensemble_times_four_and_eight_critics_beside_one(tmp_path):
    result = run_benchmark("bench_ensemble.py", tmp_path)
    assert result["threads"] == 1
    rows = {row["name"]: row for row in result["rows"]}
    assert {name: row["members"] for name, row in rows.items()} == {
        "wcsac": 1,
        "wcsac_ucb_E4": 4,
        "wcsac_ucb_E8": 8,
        "cal_E1": 1,
        "cal": 4,
        "cal_E8": 8,
    }
    for row in rows.values():
        assert_positive(row, "updates_per_s", "vs_one", "gflop_per_update", "flops_vs_one")
        baseline = rows[row["baseline"]]
        assert baseline["members"] == 1 and row["baseline"] in ("wcsac", "cal_E1")
        assert row["vs_one"] == pytest.approx(row["updates_per_s"] / baseline["updates_per_s"])
    # every member adds the same matrix work (counted exactly): linear in E
    for one, four, eight in (
        ("wcsac", "wcsac_ucb_E4", "wcsac_ucb_E8"),
        ("cal_E1", "cal", "cal_E8"),
    ):
        flops = [rows[name]["gflop_per_update"] for name in (one, four, eight)]
        assert flops[0] < flops[1] < flops[2]
        assert (flops[1] - flops[0]) / 3 == pytest.approx((flops[2] - flops[1]) / 4, rel=1e-9)


def test_bench_memory_runs_at_the_defaults_and_the_paper_options(tmp_path):
    results = run_benchmark("bench_memory.py", tmp_path)
    runs = {(r["algo"], r["full_buffer"]): r for r in results}
    assert set(runs) == {(a, f) for a in ("wcsac", "wcsac_paper") for f in (False, True)}
    for (_, full), r in runs.items():
        assert r["env"] == "tiny" and r["frames"] == 800
        # batches of 400 frames from frame 400 on (init_random_frames), 100 updates each
        assert r["updates"] == 200
        assert r["buffer_rows"] == (1500 if full else 800)
        assert_positive(r, "peak_rss_mb", "rss_end_mb", "rss_after_build_mb")
        assert r["peak_rss_mb"] >= r["rss_after_build_mb"]
        assert [frames for frames, _ in r["trace"]] == [400, 800]


def test_profile_update_gives_each_part_of_the_update_its_share(tmp_path):
    output = run_benchmark("profile_update.py", tmp_path)
    results = {r["options"]: r for r in output["profiles"]}
    assert set(results) == {"kit", "gaussian", "paper"}
    extras = {"targets: n-step draw", "kappa: start-state values"}
    common = {"targets", "online critics", "actor loss", "optimizer step"}
    for options, result in results.items():
        parts = result["parts"]
        assert common <= set(parts)
        assert extras <= set(parts) if options != "paper" else not extras & set(parts)
        for entry in parts.values():
            assert 0 <= entry["share"] <= 1 and 0 <= entry["flop_share"] <= 1
        # one repeat: the shares are of one profile and add up to it
        assert sum(e["share"] for e in parts.values()) == pytest.approx(1.0)
        assert sum(e["flop_share"] for e in parts.values()) == pytest.approx(1.0)
        assert_positive(result, "gflop_per_update")
    flops = {part: entry["flop_share"] for part, entry in results["gaussian"]["parts"].items()}
    # matrix products per row, width 16: the actor 44-16-16-4, each critic 46-16-16-1.
    # The targets run the actor, the fused product of the four target critics at s'
    # (kept whole: another grouping rounds differently) and the safety pair at s_{t+m};
    # the n-step draw the actor; the start states the actor and the safety pair alone
    # (elementwise FLOPs, also counted by the profiler, are < 1% of these)
    actor, critic = 2 * (44 * 16 + 16 * 16 + 16 * 4), 2 * (46 * 16 + 16 * 16 + 16)
    assert flops["kappa: start-state values"] / flops["targets"] == pytest.approx(
        (actor + 2 * critic) / (actor + 6 * critic), rel=0.01
    )
    assert flops["targets: n-step draw"] / flops["targets"] == pytest.approx(
        actor / (actor + 6 * critic), rel=0.01
    )
    # the cross-check without the profiler: the kit's options, each extra off, the
    # Gaussian critic, the paper's
    ablation = {row["variant"]: row["time_vs_kit"] for row in output["ablation"]}
    assert list(ablation) == [
        "kit",
        "kappa_signal=critic",
        "cost_n_steps=1",
        "kappa_statistic=mean",
        "Gaussian critic",
        "Gaussian critic, kappa_states=replay",
        "paper options",
    ]
    assert ablation["kit"] == 1.0
    assert all(math.isfinite(v) and v > 0 for v in ablation.values())


def _bench_update():
    sys.path.insert(0, str(BENCHMARKS))
    try:
        import bench_update
    finally:
        sys.path.remove(str(BENCHMARKS))
    return bench_update


def _comparable(kwargs: dict) -> dict:
    """Loss keywords with the constraint (a new module each time) as its kind and repr."""
    return {k: (type(v), repr(v)) if k == "constraint" else v for k, v in kwargs.items()}


def test_option_sets_are_what_the_trainer_and_the_loss_read():
    """``kit`` is ``python train.py``'s config; ``gaussian`` its safety critic and κ reads
    with the Gaussian critic and the study's variance head; ``paper`` ``SafetyOptions``'
    defaults, the paper's, in every keyword the loss is given."""
    bench = _bench_update()
    kit = bench.option_set("kit")
    assert kit.options.safety_critic == "iqn" and kit.options.kappa_signal == "max"
    assert safety_critic_kwargs(kit.options) == {
        "kind": "iqn",
        "num_cosines": kit.options.iqn.num_cosines,
    }
    window = (kit.options.kappa_episode_window, kit.options.kappa_episode_statistic)
    assert window == (10, "cvar")
    assert kit.extra == {"alpha_init": 0.1}
    gaussian = replace(
        kit.options,
        safety_critic="gaussian",
        variance_loss="glm",
        variance_target="td",
        kappa_signal="critic",
        kappa_episode_window=30,
        kappa_lr_scale=1.0,
    )
    for name, options in (("gaussian", gaussian), ("paper", SafetyOptions())):
        chosen = bench.option_set(name)
        expected = {**loss_parts(options), "alpha_init": 1.0}
        assert _comparable(chosen.loss_kwargs()) == _comparable(expected), name
        assert safety_critic_kwargs(chosen.options) == {
            "kind": "gaussian",
            "variance": options.variance,
        }
        assert chosen.options.kappa_signal == "critic"  # (no episode window)
    assert bench.option_set("gaussian").options.kappa_states == "initial"
    assert bench.option_set("paper").options.kappa_states == "replay"
    with pytest.raises(KeyError, match="unknown option set 'fast'"):
        bench.option_set("fast")


def test_kit_batch_carries_the_cvar_of_the_trajectories_finished_episodes():
    """The benchmark's batch for κ on the episodes: every row holds the empirical CVaR_α
    of the last ``window`` episodes its synthetic trajectories finish, computed here
    from the per-step costs (episodes restart where ``step_count`` is 0 or after a
    termination)."""
    bench = _bench_update()
    sizes = bench.Sizes(batch=8, width=16)
    loss, batch = bench.kit_loss("kit", sizes)
    traj = bench.trajectories(sizes)
    costs = []
    for row in range(traj.shape[0]):
        running = 0.0
        for t in range(traj.shape[1]):
            if traj["step_count"][row, t].item() == 0:
                running = 0.0
            running += traj["next", "cost"][row, t].item()
            if traj["next", "done"][row, t].item():
                costs.append(running)
                running = 0.0
    # the window keeps the last 10 in the order the trainer adds them (rows flattened)
    last = costs[-10:]
    worst = sorted(last, reverse=True)[: math.ceil(loss.risk_level * len(last))]
    expected = sum(worst) / len(worst)
    assert batch["episode_cvar"].shape == (8, 1)
    assert batch["episode_cvar"].flatten().tolist() == pytest.approx([expected] * 8)
    with pytest.raises(ValueError, match="kappa_signal=max reads an episode-cost window"):
        bench.pipeline_batch(loss, sizes)


def test_bench_update_times_only_the_variants_asked_for_with_their_baselines(tmp_path, capsys):
    bench = _bench_update()
    out = tmp_path / "subset.json"
    argv = [*TINY_UPDATE, "--warmup", "1", "--peak-seconds", "0.01", "--no-loop"]
    result = bench.main(
        [*argv, "--options", "kit", "--variants", "wcsac_kit_module_calls", "--json", str(out)]
    )
    rows = {row["name"]: row for row in result["updates"]}
    assert set(rows) == {"wcsac_kit_module_calls", "sac"}  # its baseline comes along
    assert rows["wcsac_kit_module_calls"]["baseline"] == "sac"
    assert json.loads(out.read_text())["updates"] == result["updates"]
    with pytest.raises(SystemExit):
        bench.main([*argv, "--options", "paper", "--variants", "wcsac_kit"])
    err = capsys.readouterr().err
    assert "--variants: unknown wcsac_kit" in err and "wcsac_paper" in err


def test_gpu_check_measures_a_training_where_it_can_and_exits_0_where_it_cannot(tmp_path):
    result = run_benchmark("gpu_check.py", tmp_path)  # --device cpu: the whole check, tiny
    (row,) = result["results"]
    assert (row["device"], row["mode"], row["epochs"]) == ("cpu", "eager", 2)
    assert_positive(row, "updates_per_s", "frames_per_s", "wall_s")
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}  # (a CUDA machine hides its cards)
    proc = subprocess.run(
        [sys.executable, str(BENCHMARKS / "gpu_check.py")],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("gpu-check: no CUDA device on this machine") and (
        len(proc.stdout.splitlines()) == 1
    ), proc.stdout
