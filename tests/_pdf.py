"""What a PDF draws, without its embedded font programs: the comparison the committed
figures are held to. Two machines with the same pinned matplotlib write the same page
content, but the subsetted TrueType/Type 1 programs (and the six-letter subset tag named
after them) depend on the fontTools and font files installed, so the PDFs' bytes differ
where nothing drawn does. :func:`pdf_drawing` keeps every object of the file (page
content, markers, colours, glyph widths, the text's Unicode map), decompressed, and
leaves out only the font programs, their glyph-id maps and the lengths and subset tags
that follow from them."""

from __future__ import annotations

import re
import zlib
from pathlib import Path

_OBJECT = re.compile(rb"(\d+) 0 obj\s*(.*?)\s*endobj", re.S)
# matplotlib writes "\nendstream" after a stream's data, whose last byte may be "\r"
_STREAM = re.compile(rb"^(.*?)\s*stream\r?\n(.*)\nendstream$", re.S)
# the objects that hold a font's program or its internal glyph-id map
_FONT_DATA = re.compile(rb"/(?:FontFile[23]?|CIDToGIDMap) (\d+) 0 R")
_CHAR_PROCS = re.compile(rb"/CharProcs\s*<<(.*?)>>", re.S)  # Type 3 glyph procedures
_REFERENCE = re.compile(rb"(\d+) 0 R")
_SUBSET_TAG = re.compile(rb"/[A-Z]{6}\+")
_LENGTHS = re.compile(rb"/Length[123]? (?:\d+ 0 R|\d+)")


def pdf_drawing(path: Path) -> dict[int, bytes]:
    """Object number -> the object with font data normalised: its dictionary with the
    lengths and subset tags removed, and its stream decompressed; a font program's object
    (FontFile, FontFile2, FontFile3, a CIDToGIDMap, a Type 3 glyph procedure) is empty,
    as is an object that only holds a stream's length."""
    data = Path(path).read_bytes()
    objects = {int(n): body for n, body in _OBJECT.findall(data)}
    if not objects:
        raise ValueError(f"{path}: no PDF objects")
    font_data = set()
    for body in objects.values():
        font_data.update(int(n) for n in _FONT_DATA.findall(body))
        for procs in _CHAR_PROCS.findall(body):
            font_data.update(int(n) for n in _REFERENCE.findall(procs))
    lengths = {int(n) for body in objects.values() for n in re.findall(rb"/Length (\d+) 0 R", body)}
    drawing = {}
    for number, body in objects.items():
        if number in font_data or number in lengths:
            drawing[number] = b""
            continue
        match = _STREAM.match(body)
        head, stream = (match.group(1), match.group(2)) if match else (body, b"")
        if b"/FlateDecode" in head:
            stream = zlib.decompress(stream)
        head = _SUBSET_TAG.sub(b"/SUBSET+", _LENGTHS.sub(b"", head))
        drawing[number] = head + (b"\nstream\n" + stream if match else b"")
    return drawing
