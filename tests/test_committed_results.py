"""The committed results are what this code makes of their committed records: a report
of ``results/<folder>/runs`` (each run's evaluation.json/.csv, config, provenance and
progress.csv, archived by ``report --archive``) writes the committed tables again, so
results and code cannot drift apart silently."""

from __future__ import annotations

import csv
import re

import pytest
from _pdf import pdf_drawing
from _training_helpers import ROOT

from paper.compare import compare_runs, format_table
from wcsac_rl.evaluation.reporting import (
    RUNS_MD,
    TABLE_CSV,
    TABLE_MD,
    TABLE_VS_PAPER,
    build_report,
)
from wcsac_rl.evaluation.run_report import IMPROVEMENT_CSV, RUN_STATISTICS_MD
from wcsac_rl.evaluation.targets import TARGETS_CSV, TARGETS_MD, write_targets
from wcsac_rl.evaluation.training_safety_table import TRAINING_SAFETY_CSV, TRAINING_SAFETY_MD

RESULTS = ROOT / "results"
FOLDERS = sorted(p.parent.name for p in RESULTS.glob("*/runs") if p.is_dir())
LAPTOP_TABLE_1 = ("evidence_static", "static_laptop", "dynamic_laptop")
README_HEADLINE = "heldout_static"  # the README's headline (held-out runs); the others are linked


def test_the_laptop_table_1_is_committed():
    assert set(LAPTOP_TABLE_1) <= set(FOLDERS)


def _improvement_pairs(folder):
    """The (A, B) row pairs of a study's committed improvement.csv, in its order."""
    path = RESULTS / folder / IMPROVEMENT_CSV
    if not path.is_file():
        return []
    pairs = [(row["a"], row["b"]) for row in _csv_rows(path)]
    return list(dict.fromkeys(pairs))


@pytest.mark.parametrize("folder", FOLDERS)
def test_report_makes_the_committed_tables_again(folder, tmp_path):
    """The report of a study's committed runs, with its own pairs (``--study --improvement``
    where it has an improvement.csv), writes its committed tables again; a held-out study's
    report is every committed file: tables, LaTeX and PNG figures byte for byte (matplotlib
    is pinned and its metadata fixed), the PDFs by what they draw (their embedded font
    programs follow the machine's fontTools and fonts: ``_pdf.pdf_drawing``), the CSVs
    within 1e-9."""
    committed = RESULTS / folder
    # the budget the committed report was made with (a study whose runs train under
    # several limits, e.g. the matched-mean control, is reported against one d)
    heading = (committed / TRAINING_SAFETY_MD).read_text().splitlines()[0]
    cost_limit = float(re.fullmatch(r"# .*, budget d = (\S+)", heading).group(1))
    pairs = _improvement_pairs(folder)
    report = build_report(
        [committed / "runs"], tmp_path, cost_limit=cost_limit, trajectories=False,
        improvement=pairs, study=bool(pairs), log=lambda _: None,
    )  # fmt: skip
    # a study in progress may hold rows of one run so far: the report leaves them out of
    # the statistics over runs in one warning, naming exactly those rows
    single = sorted(row["label"] for row in report.rows if row["seeds"] == 1)
    if single:
        assert len(report.warnings) == 1, report.warnings
        named = report.warnings[0].split(": ", 1)[1].split(", ")
        assert sorted(name.rsplit(" (", 1)[0] for name in named) == single
    else:
        assert report.warnings == []
    for name in (TABLE_MD, TABLE_VS_PAPER, RUNS_MD, TRAINING_SAFETY_MD):  # rounded numbers
        assert (tmp_path / name).is_file() == (committed / name).is_file(), name
        if (committed / name).is_file():
            assert (tmp_path / name).read_text() == (committed / name).read_text(), name
    # the csv holds full float64 reprs: means and stds of <= 200 values of magnitude
    # <= 600 summed in another order (another CPU's numpy kernels) may differ by
    # ~200 * 600 * 2**-52 ≈ 3e-11; 1e-9 bounds that and nothing a code change would do
    for name in (TABLE_CSV, TRAINING_SAFETY_CSV):
        _assert_same_csv(tmp_path / name, committed / name)
    if folder in HELD_OUT_RUNS_PLANNED:
        for name in sorted(p.name for p in tmp_path.iterdir()):
            assert (committed / name).is_file(), f"the report makes {name}, not committed"
            if name.endswith(".csv"):
                _assert_same_csv(tmp_path / name, committed / name)
            elif name.endswith(".pdf"):
                assert pdf_drawing(tmp_path / name) == pdf_drawing(committed / name), name
            else:
                assert (tmp_path / name).read_bytes() == (committed / name).read_bytes(), name


def _assert_same_csv(made_path, kept_path):
    made, kept = _csv_rows(made_path), _csv_rows(kept_path)
    assert [row.keys() for row in made] == [row.keys() for row in kept], kept_path.name
    for new, old in zip(made, kept):
        for key, value in old.items():
            # a cell of several numbers (training_safety.csv's per-seed values) word by word
            for made_word, kept_word in zip(new[key].split(" "), value.split(" "), strict=True):
                try:
                    assert float(made_word) == pytest.approx(
                        float(kept_word), rel=0, abs=1e-9, nan_ok=True
                    ), key
                except ValueError:  # a text cell
                    assert made_word == kept_word, key


def _csv_rows(path):
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.parametrize("folder", FOLDERS)
def test_the_committed_per_run_table_is_what_compare_makes_of_the_runs(folder):
    committed = RESULTS / folder / "per_run.md"
    runs = sorted((RESULTS / folder / "runs").iterdir())
    assert committed.read_text() == format_table(*compare_runs(runs)) + "\n"


def _table_rows(folder):
    table = (RESULTS / folder / TABLE_MD).read_text()
    return [line for line in table.splitlines() if line.startswith("| ")]


def test_the_readme_headline_is_the_held_out_study_and_links_every_laptop_table():
    """The README's results table is the held-out study's statistics over runs as the report
    wrote them, its probabilities of improvement are the report's, and the in-sample table
    of the tuning seeds is no longer its headline (it is linked)."""
    readme = (ROOT / "README.md").read_text()
    per_row = (RESULTS / README_HEADLINE / RUN_STATISTICS_MD).read_text().split("\n## ")[0]
    rows = [line for line in per_row.splitlines() if line.startswith("| ") and "---" not in line]
    assert len(rows) >= 4 and all(row in readme for row in rows)
    with (RESULTS / README_HEADLINE / IMPROVEMENT_CSV).open(newline="") as f:
        for pair in csv.DictReader(f):
            if pair["metric"] == "C0.1":
                p, lo, hi = (float(pair[k]) for k in ("p_a_lower", "lo", "hi"))
                assert f"{p:.2f} [{lo:.2f}, {hi:.2f}]" in readme, pair
    assert not any(row in readme for row in _table_rows("evidence_static"))
    assert "](results/README.md)" in readme
    for folder in (README_HEADLINE, *LAPTOP_TABLE_1):
        assert f"](results/{folder}/RESULTS.md)" in readme, folder


TARGETS_FILE = "targets.yaml"


@pytest.mark.parametrize("folder", [f for f in FOLDERS if (RESULTS / f / TARGETS_FILE).is_file()])
def test_the_committed_targets_table_is_its_runs_counted(folder, tmp_path):
    """A study's runs-meeting-each-target table (``targets.md``) is what its targets file
    makes of its committed report files, and the README shows the headline study's."""
    committed = RESULTS / folder
    for name in ("run_values.csv", TRAINING_SAFETY_CSV):
        (tmp_path / name).write_bytes((committed / name).read_bytes())
    write_targets(tmp_path, committed / TARGETS_FILE)
    for name in (TARGETS_MD, TARGETS_CSV):
        assert (tmp_path / name).read_bytes() == (committed / name).read_bytes(), name
    if folder == README_HEADLINE:
        readme = (ROOT / "README.md").read_text()
        assert all(line in readme for line in (committed / TARGETS_MD).read_text().splitlines())


@pytest.mark.parametrize("folder", LAPTOP_TABLE_1)
def test_each_results_page_shows_its_committed_table(folder):
    page = (RESULTS / folder / "RESULTS.md").read_text()
    rows = _table_rows(folder)
    assert len(rows) >= 9 and all(row in page for row in rows)


HELD_OUT_RUNS_PLANNED = {
    "heldout_static": 30,  # three rows × seeds 100-109
    "heldout_dynamic": 4,  # two rows × seeds 100, 101
    "heldout_learned_tail": 20,  # two rows × seeds 110-119
}


@pytest.mark.parametrize("study", sorted(HELD_OUT_RUNS_PLANNED))
def test_the_pages_count_the_held_out_runs_that_are_committed(study):
    """While a held-out study is in progress, every page that states its progress ("k of
    N runs", N its planned runs) states the number of run records committed under it."""
    planned = HELD_OUT_RUNS_PLANNED[study]
    runs = sum(1 for p in (RESULTS / study / "runs").iterdir() if p.is_dir())
    pattern = re.compile(rf"\b(\d+) of {planned} runs\b")
    pages = (ROOT / "README.md", RESULTS / "README.md", RESULTS / study / "RESULTS.md")
    for page in pages:
        counts = {int(k) for k in pattern.findall(page.read_text())}
        assert counts == ({runs} if runs < planned else counts & {runs}), (page.name, counts)


MAX_STUDY_PAGE_LINES = 300  # a study's page; its round-by-round log goes in a LOG.md beside it


def _study_pages():
    pages = [*RESULTS.glob("*/RESULTS.md"), *RESULTS.glob("*/README.md")]
    return sorted(p for p in pages if p.parent != RESULTS)


def test_every_study_page_is_within_its_length_and_indexed():
    """Each study's page is at most MAX_STUDY_PAGE_LINES lines, and results/README.md links
    every study folder (and single-page study) under results/."""
    index = (RESULTS / "README.md").read_text()
    for page in _study_pages():
        lines = len(page.read_text().splitlines())
        assert lines <= MAX_STUDY_PAGE_LINES, (str(page.relative_to(RESULTS)), lines)
        assert f"]({page.parent.name}/{page.name})" in index, page.parent.name
    for page in RESULTS.glob("*.md"):
        assert page.name == "README.md" or f"]({page.name})" in index, page.name
