"""The PDF comparison the committed figures are held to (``_pdf.pdf_drawing``): blind to
the embedded font programs, which follow the machine's fontTools and fonts, and to
nothing that is drawn."""

from __future__ import annotations

import re
import zlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import pytest
from _pdf import pdf_drawing


def _figure(path, ys, label="return"):
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot([0, 1, 2], ys, marker="o", label=label)
    ax.set_xlabel("frames")
    ax.legend()
    fig.savefig(path, metadata={"CreationDate": None})
    plt.close(fig)


def _other_font_program(data: bytes) -> bytes:
    """The same PDF as another machine's fontTools would write it: every embedded
    TrueType program (a stream with /Length1) and CIDToGIDMap replaced by other bytes of
    another length, and the subset tags renamed; offsets are not kept (a reader of the
    drawing does not use them)."""

    def program(match):
        head = re.sub(rb"/Length1 \d+ /Length \d+", b"/Length1 999 /Length 17", match.group(1))
        return head + b"stream\n" + zlib.compress(b"other glyph data") + b"\nendstream"

    data = re.sub(rb"(<< /Length1 \d+ /Length \d+ /Filter /FlateDecode >>\s*)stream\n.*?\nendstream",
                  program, data, flags=re.S)  # fmt: skip
    return re.sub(rb"/[A-Z]{6}\+", b"/QWERTY+", data)


def test_a_figure_whose_font_programs_differ_draws_the_same(tmp_path):
    _figure(tmp_path / "a.pdf", [1.0, 2.0, 1.5])
    original = (tmp_path / "a.pdf").read_bytes()
    other = _other_font_program(original)
    assert other != original and b"/QWERTY+" in other  # the font program was there to change
    (tmp_path / "b.pdf").write_bytes(other)
    assert pdf_drawing(tmp_path / "a.pdf") == pdf_drawing(tmp_path / "b.pdf")


@pytest.mark.parametrize(
    "ys, label", [([1.0, 2.0, 1.6], "return"), ([1.0, 2.0, 1.5], "cost")], ids=["data", "text"]
)
def test_a_figure_that_draws_other_data_or_text_differs(tmp_path, ys, label):
    _figure(tmp_path / "a.pdf", [1.0, 2.0, 1.5])
    _figure(tmp_path / "b.pdf", ys, label)
    assert pdf_drawing(tmp_path / "a.pdf") != pdf_drawing(tmp_path / "b.pdf")


def test_a_file_that_is_no_pdf_is_refused(tmp_path):
    (tmp_path / "x.pdf").write_bytes(b"not a pdf")
    with pytest.raises(ValueError, match="no PDF objects"):
        pdf_drawing(tmp_path / "x.pdf")
