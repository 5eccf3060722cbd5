"""The report's runs one by one and statistics over them (wcsac_rl.evaluation.run_report),
made from committed runs (results/evidence_static/runs: seeds 0, 10, 20, in-sample).

Tolerances: run values are float64 means and CVaRs of 100 episode costs of magnitude
<= 500 (another summation order: <= 100 × 500 × 2⁻⁵² ≈ 1e-11); 1e-9 bounds that, and
evaluation.json holds the same metrics computed by the evaluator.
"""

from __future__ import annotations

import csv
import json
import shutil

import pytest
from _hostile_helpers import copy_study
from _training_helpers import ROOT, tree_digests

from wcsac_rl.evaluation.reporting import ReportError, build_report
from wcsac_rl.evaluation.run_report import (
    FIG_RUNS,
    FIG_SCORE,
    IMPROVEMENT_CSV,
    RUN_STATISTICS_CSV,
    RUN_STATISTICS_MD,
    RUN_VALUES_CSV,
    RUN_VALUES_MD,
)
from wcsac_rl.report import main as report_main

RUNS = ROOT / "results" / "evidence_static" / "runs"
PAIRS = (("wcsac_0.1", "sac_lag"), ("wcsac_0.1", "sac_lag_d1.5"))
NEW_FILES = (RUN_VALUES_MD, RUN_VALUES_CSV, RUN_STATISTICS_MD, RUN_STATISTICS_CSV,
             IMPROVEMENT_CSV, FIG_RUNS, FIG_SCORE)  # fmt: skip
ABS = 1e-9


def _quiet(_line: str) -> None:
    pass


@pytest.fixture(scope="module")
def twice(tmp_path_factory):
    """The committed study reported twice, into two directories."""
    outs = []
    for name in ("first", "second"):
        out = tmp_path_factory.mktemp(name)
        report = build_report(
            [RUNS], out, cost_limit=15.0, trajectories=False, improvement=PAIRS, log=_quiet
        )
        outs.append((out, report))
    return outs


def test_the_report_is_byte_identical_when_made_again(twice):
    (first, report), (second, again) = twice
    assert report.warnings == again.warnings == []
    names = sorted(p.name for p in report.files)
    assert names == sorted(p.name for p in again.files)
    assert set(NEW_FILES) <= set(names)
    for name in names:
        assert (first / name).read_bytes() == (second / name).read_bytes(), name
    for name in (FIG_RUNS, FIG_SCORE):
        assert b"matplotlib" not in (first / name).read_bytes()  # no software stamp


def test_the_new_files_are_not_overwritten_without_force(twice):
    (first, _), _ = twice
    before = tree_digests(first)
    with pytest.raises(ReportError, match=r"already has .*run_values\.md.*fig_runs\.png"):
        build_report(
            [RUNS], first, cost_limit=15.0, trajectories=False, improvement=PAIRS, log=_quiet
        )
    assert tree_digests(first) == before


def _rows(path):
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_each_run_is_one_line_with_its_own_evaluation(twice):
    (out, _), _ = twice
    rows = _rows(out / RUN_VALUES_CSV)
    assert len(rows) == len(list(RUNS.iterdir())) == 27
    for row in rows:
        meta = json.loads((RUNS / row["run"] / "evaluation.json").read_text())
        assert (row["label"], int(row["seed"])) == (meta["label"], meta["seed"])
        for key in ("EC", "C0.1", "ER"):
            assert float(row[key]) == pytest.approx(meta["metrics"][key], abs=ABS), key
        assert float(row["goals"]) == pytest.approx(meta["goals_per_episode"], abs=ABS)
        assert row["split"] == "in-sample" and row["machine"] == "not recorded"
    md = (out / RUN_VALUES_MD).read_text().splitlines()
    assert md[2] == "| row | seed | split | machine | EC | C0.1 | ER | goals | episodes | run |"
    assert md[4].startswith("| SAC | 0 | in-sample | not recorded | ")


def test_three_runs_a_row_iqm_is_their_mean_and_the_pairs_read_as_in_sample(twice):
    (out, _), _ = twice
    values = _rows(out / RUN_VALUES_CSV)
    stats = {row["label"]: row for row in _rows(out / RUN_STATISTICS_CSV)}
    assert len(stats) == 9
    for label, row in stats.items():
        mine = [float(v["C0.1"]) for v in values if v["label"] == label]
        assert row["runs"] == "3" and row["held_out_runs"] == "0"
        # ⌊3/4⌋ = 0 runs cut: the IQM of three runs is their mean
        assert float(row["C0.1_iqm"]) == pytest.approx(sum(mine) / 3, abs=ABS)
        assert float(row["C0.1_lo"]) <= float(row["C0.1_iqm"]) <= float(row["C0.1_hi"])
    pairs = {(r["a"], r["b"], r["metric"]): r for r in _rows(out / IMPROVEMENT_CSV)}
    assert list(pairs) == [(a, b, m) for a, b in PAIRS for m in ("C0.1", "EC", "ER")]
    # every WCSAC-0.1 run has a lower C0.1 than every SAC-Lag run: P = 1 in all resamples
    ours = [float(v["C0.1"]) for v in values if v["label"] == "wcsac_0.1"]
    theirs = [float(v["C0.1"]) for v in values if v["label"] == "sac_lag"]
    assert max(ours) < min(theirs)
    lag = pairs[("wcsac_0.1", "sac_lag", "C0.1")]
    assert (float(lag["p_a_lower"]), float(lag["lo"]), float(lag["hi"])) == (1.0, 1.0, 1.0)
    assert lag["reading"] == "WCSAC-0.1 lower; not a claim: in-sample runs"
    # against the matched-mean control, by hand over the 9 pairs of runs
    control = [float(v["C0.1"]) for v in values if v["label"] == "sac_lag_d1.5"]
    by_hand = sum((x < y) + 0.5 * (x == y) for x in ours for y in control) / 9
    matched = pairs[("wcsac_0.1", "sac_lag_d1.5", "C0.1")]
    assert float(matched["p_a_lower"]) == pytest.approx(by_hand, abs=ABS)
    assert float(matched["lo"]) <= 0.5 and matched["reading"] == "within noise"
    # the return too: P(a run of A returns less), by hand over the 9 pairs of runs
    er = {
        lab: [float(v["ER"]) for v in values if v["label"] == lab]
        for lab in ("wcsac_0.1", "sac_lag")
    }
    by_hand = sum((x < y) + 0.5 * (x == y) for x in er["wcsac_0.1"] for y in er["sac_lag"]) / 9
    returns = pairs[("wcsac_0.1", "sac_lag", "ER")]
    assert float(returns["p_a_lower"]) == pytest.approx(by_hand, abs=ABS)
    md = (out / RUN_STATISTICS_MD).read_text()
    assert (
        "| WCSAC-0.1 | SAC-Lag (d=1.5) | C0.1 | " in md and "| 3 (0), 3 (0) | within noise |" in md
    )


# ------------------------------------------------------------------------ bad input
@pytest.fixture
def study(tmp_path):
    """Two rows of three archived runs each (WCSAC-0.1, SAC-Lag)."""
    return copy_study(tmp_path / "study")


def _refused(study, tmp_path, capsys, args, *needles):
    """The CLI refuses with one ``error:`` line holding ``needles``; nothing changes."""
    out = tmp_path / "out"
    before = tree_digests(tmp_path)
    code = report_main([str(study), "--out", str(out), "--no-trajectories", *args])
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 1 and "Traceback" not in err
    assert len(errors) == 1, err
    for needle in needles:
        assert needle in errors[0], errors[0]
    assert tree_digests(tmp_path) == before and not out.exists()


def test_a_row_of_one_run_is_refused_in_a_study(study, tmp_path, capsys):
    for seed in (10, 20):
        shutil.rmtree(study / f"sac_lag_static_seed{seed}")
    _refused(study, tmp_path, capsys, ["--study"],
             "statistics over runs need >= 2 runs of a row; found 1 of row(s) sac_lag (1)")  # fmt: skip
    _refused(study, tmp_path, capsys, ["--improvement", "wcsac_0.1:sac_lag"], "found 1")


def test_runs_of_other_settings_in_a_row_are_refused_naming_the_key(study, tmp_path, capsys):
    config = study / "sac_lag_static_seed10" / "config.yaml"
    text = config.read_text()
    assert "  kappa_lr_scale: 0.3\n" in text
    config.write_text(text.replace("  kappa_lr_scale: 0.3\n", "  kappa_lr_scale: 0.5\n"))
    _refused(study, tmp_path, capsys, ["--study"],
             "the runs of row sac_lag were made with different settings: algo.kappa_lr_scale "
             "(0.3: sac_lag_static_seed0, sac_lag_static_seed20; 0.5: sac_lag_static_seed10)")  # fmt: skip


def test_an_option_some_runs_of_a_row_lack_is_not_a_difference(study, tmp_path):
    """A run made before an option existed (its config lacks the key; it trained at the
    option's default) pools with runs that have it, as Table 1's rows do."""
    config = study / "sac_lag_static_seed0" / "config.yaml"
    config.write_text(
        config.read_text().replace(
            "  kappa_lr_scale: 0.3\n", "  kappa_lr_scale: 0.3\n  new_option: 1.0\n"
        )
    )
    out = tmp_path / "out"
    assert report_main([str(study), "--out", str(out), "--no-trajectories", "--study"]) == 0
    assert (out / RUN_STATISTICS_MD).is_file()


def test_an_interpolation_in_a_runs_config_is_compared_as_written(
    study, tmp_path, capsys, monkeypatch
):
    """A ``${...}`` in a run's config.yaml is data: it is compared as written and never
    resolved, so no environment variable is read because a file says so."""
    monkeypatch.setenv("WCSAC_SECRET", "0.3")  # resolved, it would equal the other runs'
    config = study / "sac_lag_static_seed20" / "config.yaml"
    config.write_text(
        config.read_text().replace(
            "  kappa_lr_scale: 0.3\n", "  kappa_lr_scale: ${oc.env:WCSAC_SECRET}\n"
        )
    )
    _refused(study, tmp_path, capsys, ["--study"],
             "algo.kappa_lr_scale", "'${oc.env:WCSAC_SECRET}': sac_lag_static_seed20")  # fmt: skip


def test_a_seed_twice_in_a_row_is_refused(study, tmp_path, capsys):
    shutil.copytree(study / "sac_lag_static_seed10", study / "copy_of_seed10")
    _refused(study, tmp_path, capsys, ["--study"], "row sac_lag has several runs of seed(s) 10")


@pytest.mark.parametrize("missing", [("evaluation.csv",), ("evaluation.json", "evaluation.csv")])
def test_a_run_without_its_evaluation_files_is_refused(study, tmp_path, capsys, missing):
    for name in missing:
        (study / "sac_lag_static_seed20" / name).unlink()
    _refused(study, tmp_path, capsys, ["--improvement", "wcsac_0.1:sac_lag"],
             "1 run(s) have no readable evaluation", "sac_lag_static_seed20")  # fmt: skip


@pytest.mark.parametrize(
    ("pair", "needle"),
    [
        ("wcsac_0.1:sac_lag_d1.5", "--improvement wcsac_0.1:sac_lag_d1.5: no row 'sac_lag_d1.5' "
         "(rows: sac_lag, wcsac_0.1)"),
        ("wcsac_0.1", "--improvement takes A:B, two row labels"),
        ("a:b:c", "--improvement takes A:B, two row labels"),
    ],
)  # fmt: skip
def test_an_improvement_pair_naming_no_row_is_refused(study, tmp_path, capsys, pair, needle):
    _refused(study, tmp_path, capsys, ["--improvement", pair], needle)


def test_a_plain_report_leaves_the_statistics_out_in_one_warning_line(study, tmp_path, capsys):
    """Without --study, runs that cannot be pooled leave out the statistics over runs (one
    warning line); the rest of the report is made."""
    shutil.copytree(study / "sac_lag_static_seed10", study / "copy_of_seed10")
    out = tmp_path / "out"
    assert report_main([str(study), "--out", str(out), "--no-trajectories"]) == 0
    captured = capsys.readouterr()
    lines = [line for line in (captured.out + captured.err).splitlines() if "per-run" in line]
    assert lines == [
        "warning: per-run statistics skipped: row sac_lag has several runs of seed(s) 10: "
        "statistics over runs count each seed once"
    ]
    assert (out / "table1.md").is_file()
    assert not any((out / name).exists() for name in NEW_FILES)


def test_a_plain_report_of_one_run_lists_it_and_says_it_has_no_statistics(study, tmp_path):
    lines: list[str] = []
    report = build_report(
        [study / "sac_lag_static_seed0"], tmp_path / "out", trajectories=False, log=lines.append
    )
    assert report.warnings == [
        "row(s) of one run left out of the statistics over runs: sac_lag (1)"
    ]
    out = tmp_path / "out"
    assert len(_rows(out / RUN_VALUES_CSV)) == 1 and _rows(out / RUN_STATISTICS_CSV) == []
    assert (
        "Left out (one run: no statistics over runs): SAC-Lag."
        in (out / RUN_STATISTICS_MD).read_text()
    )
    assert (out / FIG_RUNS).is_file() and (out / FIG_SCORE).is_file()


# ------------------------------------------------------------- held-out runs, claims
def _evaluation(tmp_path, label, seed, costs, machine=None):
    """An evaluation of ``label`` at ``seed`` with these episode costs (return 1 - cost/100)."""
    from wcsac_rl.evaluation.evaluator import Evaluation
    from wcsac_rl.rollouts.episodes import EpisodeResult

    directory = tmp_path / f"{label}_seed{seed}"
    directory.mkdir()
    if machine is not None:
        record = {"machine": {"processor": machine[0], "cpu_capability": machine[1]}}
        (directory / "provenance.json").write_text(json.dumps(record))
    episodes = [EpisodeResult(1.0 - c / 100, c, 1000, 1, False) for c in costs]
    meta = {"label": label, "env": "static", "seed": seed, "cost_limit": 15.0,
            "env_seed": 2_000_003 + seed, "episodes": len(costs)}  # fmt: skip
    return Evaluation(directory=directory, meta=meta, episodes=episodes)


def _study(tmp_path, seeds, shift):
    """Rows ``a`` (run i: ten episodes of cost i) and ``b`` (cost i + ``shift``) on ``seeds``,
    their runs alternating between two machines."""
    from wcsac_rl.evaluation.run_report import collect_run_statistics

    xeon, epyc = ("Xeon", "AVX512"), ("EPYC", "AVX2")
    evaluations = [
        _evaluation(tmp_path, label, seed, [i + extra] * 10, machine=xeon if i % 2 else epyc)
        for label, extra in (("a", 0.0), ("b", shift))
        for i, seed in enumerate(seeds)
    ]
    return collect_run_statistics(
        evaluations, [], env="static", cost_limit=15.0, config_of=lambda _: None,
        improvement=[("a", "b")],
    )  # fmt: skip


def test_ten_held_out_runs_a_row_that_separate_make_a_claim(tmp_path):
    stats = _study(tmp_path, range(100, 110), shift=50.0)
    c01, ec, _er = stats.improvements
    assert (c01["metric"], c01["p_a_lower"], c01["lo"], c01["hi"]) == ("C0.1", 1.0, 1.0, 1.0)
    assert c01["reading"] == ec["reading"] == "a lower"
    row = stats.rows[0]
    assert (row["runs"], row["held_out_runs"]) == (10, 10)
    assert row["machines"] == "EPYC (AVX2): 5; Xeon (AVX512): 5"
    assert [run["machine"] for run in stats.runs[:2]] == ["EPYC (AVX2)", "Xeon (AVX512)"]
    # C0.1 of a run of ten equal episodes is that cost; IQM of 0..9: the middle 6, 2..7
    assert row["C0.1_iqm"] == pytest.approx(4.5, abs=ABS)
    assert row["EC_iqm"] == pytest.approx(4.5, abs=ABS)


def test_orderings_of_few_or_in_sample_runs_are_no_claim_and_overlap_is_noise(tmp_path):
    for name in ("few", "tuned", "noise"):
        (tmp_path / name).mkdir()
    few = _study(tmp_path / "few", range(100, 105), shift=50.0)
    assert few.improvements[0]["reading"] == (
        "a lower; not a claim: fewer than 10 held-out runs a row"
    )
    tuned = _study(tmp_path / "tuned", (0, 1, 10, 20, 30, 40, 50, 60, 70, 100), shift=50.0)
    assert tuned.improvements[0]["reading"] == "a lower; not a claim: in-sample runs"
    assert tuned.rows[0]["held_out_runs"] == 1
    noise = _study(tmp_path / "noise", range(100, 110), shift=0.5)
    entry = noise.improvements[0]
    # run i of a is below run j of b (cost j + 0.5) for i <= j: 55 of 100 pairs
    assert entry["p_a_lower"] == pytest.approx(0.55, abs=ABS)
    assert entry["lo"] <= 0.5 <= entry["hi"] and entry["reading"] == "within noise"
