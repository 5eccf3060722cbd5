"""The side-by-side table of evaluated runs (paper.compare).

Tolerances: float64 arithmetic on a few hand-written numbers; approx's default
``rel=1e-6`` is 10⁹ float64 roundings.
"""

from __future__ import annotations

import json
import math

import pytest

from paper.compare import compare_runs, format_table, main


def _run(tmp_path, name, label, seed, ec, c01, ratio=None, kappa=0.5, calibrated=True):
    run = tmp_path / name
    run.mkdir()
    # (C_α = EC/α, as where >= 1 - α of the episodes cost 0)
    metrics = {"EC": ec, "C0.9": ec / 0.9, "C0.5": 2 * ec, "C0.1": c01, "ER": 0.5}
    metrics["over_budget"] = 0.1
    (run / "evaluation.json").write_text(
        json.dumps({"label": label, "seed": seed, "trained_frames": 300000, "metrics": metrics})
    )
    (run / "progress.csv").write_text(
        f"epoch,time_s,loss/kappa,train/cost_rate\n1,60,1.0,0.5\n2,1200,{kappa},0.02\n"
    )
    if calibrated:
        calib = {"start_cvar": 8.0, "start_realised_cvar": 4.0, "start_cvar_ratio": ratio}
        (run / "calibration.json").write_text(json.dumps({"metrics": calib}))
    return run


def test_rows_and_per_label_means(tmp_path):
    runs = [
        _run(tmp_path, "a0", "wcsac_x", 0, ec=10.0, c01=40.0, ratio=2.0, kappa=1.0),
        _run(tmp_path, "a1", "wcsac_x", 1, ec=20.0, c01=60.0, ratio=None, kappa=3.0),
        _run(tmp_path, "b0", "sac_lag", 0, ec=5.0, c01=30.0, calibrated=False),
    ]
    rows, means = compare_runs(runs)
    assert [r["label"] for r in rows] == ["wcsac_x", "wcsac_x", "sac_lag"]
    assert rows[0]["minutes"] == pytest.approx(20.0)
    assert rows[0]["kappa"] == pytest.approx(1.0)
    assert rows[0]["cost_rate"] == pytest.approx(0.02)
    assert math.isnan(rows[1]["start_cvar_ratio"])  # null in calibration.json
    assert math.isnan(rows[2]["start_cvar"])  # no calibration.json at all
    assert [m["label"] for m in means] == ["wcsac_x", "sac_lag"]
    assert means[0]["EC"] == pytest.approx(15.0)
    assert means[0]["C0.1"] == pytest.approx(50.0)
    assert means[0]["kappa"] == pytest.approx(2.0)
    assert means[0]["start_cvar_ratio"] == pytest.approx(2.0)  # NaNs left out of the mean
    table = format_table(rows, means)
    lines = table.splitlines()
    assert len(lines) == 2 + 3 + 2
    assert means[0]["C0.5"] == pytest.approx(30.0)
    assert "| wcsac_x | mean of 2 | 300000 | 20.00 | 15.00 | 16.67 | 30.00 | 50.00 |" in table
    assert lines[4].count("—") >= 5  # the uncalibrated SAC-Lag run


def test_cli_writes_the_table_and_refuses_unevaluated_runs(tmp_path, capsys):
    run = _run(tmp_path, "a0", "wcsac_x", 0, ec=10.0, c01=40.0, ratio=2.0)
    out = tmp_path / "table.md"
    main([str(run), "--out", str(out)])
    assert out.read_text().strip() == capsys.readouterr().out.strip()
    (tmp_path / "bare").mkdir()
    with pytest.raises(SystemExit) as stop:  # one line, not a traceback
        main([str(run), str(tmp_path / "bare")])
    assert (
        stop.value.code
        == f"error: {tmp_path / 'bare'}: no evaluation.json (run python -m wcsac_rl.evaluate)"
    )
    torn = _run(tmp_path, "torn", "wcsac_x", 0, ec=1.0, c01=1.0)
    (torn / "evaluation.json").write_text('{"label": "wcsac_x"')
    with pytest.raises(SystemExit, match=r"^error: "):
        main([str(torn)])
