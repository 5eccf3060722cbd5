"""Readers of a run's records read only whole data (issue 33): a row a killed process left
half-written is skipped with one warning line, never parsed into a wrong number."""

from __future__ import annotations

import math

import pytest

from wcsac_rl.training.progress import read_progress

HEADER = "epoch,frames,train/episode_cost\r\n"
WHOLE = "1,400,3.5\r\n2,800,2.25\r\n"


@pytest.mark.parametrize(
    ("tail", "why"),
    [
        ("3,1200,1.", "a number cut short (no line end)"),
        ("3,1200,12\r\n"[:-2], "the last row without its line end"),
        ("3,12\r\n", "fewer fields"),
        ("3,1200,1.5,9\r\n", "more fields"),
        ("3,1200,1.2e\r\n", "not a number"),
    ],
)
def test_a_half_written_last_row_is_skipped_with_one_warning_line(tmp_path, capsys, tail, why):
    path = tmp_path / "progress.csv"
    path.write_text(HEADER + WHOLE + tail, newline="")
    columns = read_progress(path)
    assert columns["frames"] == [400.0, 800.0], why
    assert columns["train/episode_cost"] == [3.5, 2.25]
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"warning: {path}: skipped 1 incomplete row")
    read_progress(path, warn=False)
    assert capsys.readouterr().err == ""


def test_whole_rows_and_empty_cells_read_without_a_warning(tmp_path, capsys):
    path = tmp_path / "progress.csv"
    path.write_text(HEADER + WHOLE + "3,1200,\r\n", newline="")
    columns = read_progress(path)
    assert columns["frames"] == [400.0, 800.0, 1200.0]
    assert math.isnan(columns["train/episode_cost"][2])
    assert capsys.readouterr().err == ""
    path.write_text("epoch,fra", newline="")  # killed while writing the header
    assert read_progress(path) == {}
