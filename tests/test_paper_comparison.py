"""``table1_vs_paper.md``: a report's Table 1 beside the paper's, and the orderings."""

from __future__ import annotations

from wcsac_rl.evaluation.paper import PAPER_TABLE1, paper_comparison_markdown


def _row(label: str, ec: float, c01: float) -> dict:
    return {"label": label, "EC": ec, "C0.9": ec + 1, "C0.5": ec + 2, "C0.1": c01, "ER": 0.5}


def _table(markdown: str) -> dict[str, list[str]]:
    rows = {}
    for line in markdown.splitlines():
        if line.startswith("| ") and not line.startswith("| Algorithm"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows[cells[0]] = cells[1:]
    return rows


def test_rows_sit_beside_the_papers_and_kit_rows_beside_their_paper_row():
    rows = [
        _row("sac", 18.64, 52.8),
        _row("sac_lag", 15.2, 54.0),
        _row("sac_lag_paper", 6.0, 40.9),
        _row("wcsac_0.1", 2.75, 25.1),
        _row("wcsac_iqn_0.1", 2.83, 25.7),
        _row("mine", 1.0, 1.0),  # no paper row: left out
    ]
    md = paper_comparison_markdown(rows, "static", 15.0)
    assert md.startswith("# Table 1 here and in the paper — StaticEnv, budget d = 15\n")
    table = _table(md)
    assert list(table) == ["SAC", "SAC-Lag", "SAC-Lag-paper", "WCSAC-0.1", "WCSAC-IQN-0.1"]
    paper = PAPER_TABLE1["static"]
    # EC here, EC paper, C0.9 here, ..., ER paper; the paper row named in column 1
    here_and_paper = ["18.64", "21.70", "19.64", "24.10", "20.64", "42.80", "52.80", "56.50"]
    assert table["SAC"] == ["SAC", *here_and_paper, "0.50", "0.97"]
    assert table["SAC-Lag-paper"][:3] == ["SAC-Lag", "6.00", f"{paper['sac_lag']['EC']:.2f}"]
    assert table["WCSAC-IQN-0.1"][0] == "WCSAC-0.1"
    assert table["WCSAC-IQN-0.1"][8] == "14.30"  # C0.1 of the paper's WCSAC-0.1
    # the orderings use the paper's own labels: SAC, SAC-Lag, WCSAC-0.1
    assert "C0.1, lowest first — here: WCSAC-0.1 < SAC < SAC-Lag" in md
    assert "C0.1, lowest first — paper: WCSAC-0.1 < SAC < SAC-Lag" in md
    assert "EC, lowest first — here: WCSAC-0.1 < SAC-Lag < SAC" in md
    assert "EC, lowest first — paper: WCSAC-0.1 < SAC-Lag < SAC" in md
    assert md.count("(the same order over the 3 rows both tables have)") == 2


def test_a_different_order_is_said_and_ties_are_shown():
    rows = [_row("sac", 10.0, 30.0), _row("wcsac_0.1", 10.0, 60.0)]
    md = paper_comparison_markdown(rows, "static", 15.0)
    assert "C0.1, lowest first — here: SAC < WCSAC-0.1" in md
    assert "C0.1, lowest first — paper: WCSAC-0.1 < SAC" in md
    assert "(a different order over the 2 rows both tables have)" in md
    assert "EC, lowest first — here: SAC = WCSAC-0.1" in md  # equal ECs


def test_an_order_of_fewer_runs_than_a_claim_needs_says_it_is_not_a_finding():
    rows = [{**_row("sac", 10.0, 30.0), "runs": 10}, {**_row("wcsac_0.1", 5.0, 9.0), "runs": 3}]
    md = paper_comparison_markdown(rows, "static", 15.0)
    caveat = "; not a finding: 3 run(s) in a row, an ordering needs 10)"
    assert md.count(f"(the same order over the 2 rows both tables have{caveat}") == 2
    rows[1]["runs"] = 10
    md = paper_comparison_markdown(rows, "static", 15.0)
    assert md.count("(the same order over the 2 rows both tables have)") == 2


def test_no_comparison_where_the_paper_has_no_table_or_another_budget():
    rows = [_row("sac", 10.0, 30.0)]
    assert paper_comparison_markdown(rows, "dynamic", 15.0) is None
    assert paper_comparison_markdown(rows, "static", 10.0) is None
    assert paper_comparison_markdown([_row("mine", 1.0, 1.0)], "static", 15.0) is None


def test_the_numbers_are_the_papers_as_docs_paper_md_quotes_them():
    from _training_helpers import ROOT

    from wcsac_rl.evaluation.runs import row_name

    text = (ROOT / "docs" / "paper.md").read_text()
    section = text.split("## Table 1 (StaticEnv)", 1)[1].split("\n## ", 1)[0]
    quoted = _table(section.replace("| | EC |", "| Algorithm | EC |"))
    names = {row_name(label): label for label in PAPER_TABLE1["static"]}
    assert set(quoted) == set(names)
    for name, cells in quoted.items():
        row = PAPER_TABLE1["static"][names[name]]
        assert [float(c) for c in cells] == [row[k] for k in ("EC", "C0.9", "C0.5", "C0.1", "ER")]


def test_rows_compared_only_through_another_label_give_no_ordering():
    """A report of paper-variant rows alone (``wcsac_paper_0.1`` beside the paper's
    WCSAC-0.1) writes the side-by-side table and says there is no ordering, instead of
    failing."""
    from wcsac_rl.evaluation.paper import paper_comparison_markdown

    row = {"label": "wcsac_paper_0.1", "EC": 2.0, "C0.9": 2.2, "C0.5": 4.0, "C0.1": 20.0, "ER": 0.1}
    text = paper_comparison_markdown([row], "static", 15.0)
    assert "| WCSAC-paper-0.1 | WCSAC-0.1 |" in text
    assert "No ordering: none of the paper's own rows here." in text
