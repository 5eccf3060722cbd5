"""The report's tables as LaTeX ``booktabs`` tables (``<table>.tex`` beside ``<table>.md``).

:func:`markdown_to_latex` turns every pipe table of a Markdown text into a ``table``
environment, captioned with the heading above it, its cells' symbols in math mode, so that
the file compiles with ``\\usepackage{booktabs}`` alone; the same table gives the same
bytes. Text from a run's files goes into a Markdown table through :func:`markdown_cell`
and into a title through :func:`markdown_text`: a bar cannot split its cell and a line
break cannot end its row. :func:`markdown_table` and :func:`csv_text` write the tables.
"""

from __future__ import annotations

import csv
import io
import re
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

__all__ = [
    "csv_text",
    "latex_path",
    "latex_text",
    "markdown_cell",
    "markdown_table",
    "markdown_text",
    "markdown_to_latex",
]

_SPECIAL = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "$": r"\$",
    "#": r"\#",
    "_": r"\_",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
}
_SYMBOLS = {
    "α": r"$\alpha$",
    "β": r"$\beta$",
    "γ": r"$\gamma$",
    "κ": r"$\kappa$",
    "Γ": r"$\Gamma$",
    "≤": r"$\leq$",
    "≥": r"$\geq$",
    "±": r"$\pm$",
    "×": r"$\times$",
    "·": r"$\cdot$",
    "⌈": r"$\lceil$",
    "⌉": r"$\rceil$",
    "→": r"$\rightarrow$",
    "↑": r"$\uparrow$",
    "½": r"$\frac{1}{2}$",
    "–": "--",
    "—": "---",
    "…": r"\ldots{}",
    "\u2009": r"\,",
    "\ufffd": "?",
}


_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029]")
"""Characters that end or garble a line of text: line breaks, tabs and other controls."""


def markdown_text(text: object) -> str:
    """``text`` on one line: each line break, tab or other control character written as
    its Python escape (``\\n``, ``\\t``, ``\\x1b``); any other text unchanged.

    >>> markdown_text("run\\nname"), markdown_text("WCSAC-0.5")
    ('run\\\\nname', 'WCSAC-0.5')
    """
    return _CONTROL.sub(lambda m: repr(m.group())[1:-1], str(text))


def markdown_cell(text: object) -> str:
    """``text`` as one cell of a Markdown pipe table (:func:`markdown_text`, and each bar
    ``|`` written ``\\|``, which :func:`markdown_to_latex` reads back as a bar); any other
    text unchanged.

    >>> markdown_cell("wcsac|x"), markdown_cell("sac_lag[cost_limit=1.5]")
    ('wcsac\\\\|x', 'sac_lag[cost_limit=1.5]')
    """
    return markdown_text(text).replace("|", "\\|")


def markdown_table(header: Sequence[str], align: str, rows: Iterable[Sequence[Any]]) -> list[str]:
    """The lines of a Markdown pipe table: ``align`` holds one ``l`` (left) or ``r``
    (right) per column; the cells are written as given (:func:`markdown_cell` them first).

    >>> markdown_table(["a", "b"], "lr", [["x", 1]])
    ['| a | b |', '|---|---:|', '| x | 1 |']
    """
    return [
        "| " + " | ".join(header) + " |",
        "|" + "".join("---:|" if a == "r" else "---|" for a in align),
        *("| " + " | ".join(map(str, row)) + " |" for row in rows),
    ]


def csv_text(
    rows: Iterable[Mapping[str, Any]], columns: Sequence[str], lineterminator: str = "\n"
) -> str:
    """``rows`` as CSV text with a header of ``columns`` (other keys of a row left out)."""
    buf = io.StringIO()
    writer = csv.DictWriter(
        buf, fieldnames=columns, extrasaction="ignore", lineterminator=lineterminator
    )
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def latex_text(text: str) -> str:
    """``text`` as LaTeX: special characters escaped, the tables' symbols in math mode,
    ``**bold**`` as ``\\textbf{bold}`` and `` `code` `` as ``\\texttt{code}``.

    >>> latex_text("**12.50** [1.0, 2.0] 5% of C_α ≤ d")
    '\\\\textbf{12.50} [1.0, 2.0] 5\\\\% of C\\\\_$\\\\alpha$ $\\\\leq$ d'
    """
    out: list[str] = []
    for part in re.split(r"(\*\*[^*]+\*\*|`[^`]+`)", text):
        if part.startswith("**") and part.endswith("**") and len(part) > 4:
            out.append(r"\textbf{" + latex_text(part[2:-2]) + "}")
        elif part.startswith("`") and part.endswith("`") and len(part) > 2:
            out.append(r"\texttt{" + latex_text(part[1:-1]) + "}")
        else:
            out.append("".join(_SPECIAL.get(c, _SYMBOLS.get(c, c)) for c in part))
    return "".join(out)


def _cells(line: str) -> list[str]:
    """A Markdown table line's cells (``\\|`` inside a cell kept as a bar)."""
    inner = line.strip()
    inner = inner[1:] if inner.startswith("|") else inner
    inner = inner[:-1] if inner.endswith("|") and not inner.endswith("\\|") else inner
    return [cell.strip().replace("\\|", "|") for cell in re.split(r"(?<!\\)\|", inner)]


def _alignment(separator: str) -> str:
    columns = []
    for cell in _cells(separator):
        right, left = cell.endswith(":"), cell.startswith(":")
        columns.append("c" if right and left else "r" if right else "l")
    return "".join(columns)


def _is_separator(line: str) -> bool:
    return bool(re.fullmatch(r"\|?(\s*:?-+:?\s*\|)+\s*:?-*:?\s*", line.strip()))


def _tables(markdown: str) -> list[tuple[str, list[str]]]:
    """``(heading, table lines)`` per pipe table: the nearest ``#`` heading above it."""
    found: list[tuple[str, list[str]]] = []
    heading, block = "", []
    lines = markdown.splitlines()
    for i, line in enumerate([*lines, ""]):
        if line.startswith("|"):
            block.append(line)
            continue
        if len(block) >= 2 and _is_separator(block[1]):
            found.append((heading, block))
        block = []
        if line.startswith("#") and i < len(lines):
            heading = line.lstrip("#").strip()
    return found


def markdown_to_latex(markdown: str) -> str:
    """Every pipe table of ``markdown`` as a booktabs ``table`` (see the module docstring).

    >>> print(markdown_to_latex("# T\\n\\n| a | b |\\n|---|---:|\\n| x_1 | **2** |\\n"))
    % booktabs tables (\\usepackage{booktabs}); from the Markdown table of the same name
    \\begin{table}[ht]
    \\centering
    \\caption{T}
    \\begin{tabular}{lr}
    \\toprule
    a & b \\\\
    \\midrule
    x\\_1 & \\textbf{2} \\\\
    \\bottomrule
    \\end{tabular}
    \\end{table}
    <BLANKLINE>

    Raises:
        ValueError: ``markdown`` has no table, or a row has another number of cells
            than its header.
    """
    tables = _tables(markdown)
    if not tables:
        raise ValueError("the Markdown text has no table to write as LaTeX")
    out = ["% booktabs tables (\\usepackage{booktabs}); from the Markdown table of the same name"]
    for heading, lines in tables:
        header, align, body = _cells(lines[0]), _alignment(lines[1]), lines[2:]
        if len(align) != len(header):
            raise ValueError(f"table {heading!r}: its separator has {len(align)} columns")
        out += [r"\begin{table}[ht]", r"\centering"]
        if heading:
            out.append(r"\caption{" + latex_text(heading) + "}")
        out += [r"\begin{tabular}{" + align + "}", r"\toprule"]
        out.append(" & ".join(latex_text(cell) for cell in header) + r" \\")
        out.append(r"\midrule")
        for line in body:
            cells = _cells(line)
            if len(cells) != len(header):
                raise ValueError(
                    f"table {heading!r}: a row has {len(cells)} cells, its header "
                    f"{len(header)}: {line!r}"
                )
            out.append(" & ".join(latex_text(cell) for cell in cells) + r" \\")
        out += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(out) + "\n"


def latex_path(markdown_name: str) -> str:
    """The ``.tex`` file beside a Markdown table: ``table1.md`` → ``table1.tex``."""
    stem, dot, suffix = markdown_name.rpartition(".")
    if not dot or suffix != "md":
        raise ValueError(f"{markdown_name!r} is not a Markdown file name (.md)")
    return f"{stem}.tex"
