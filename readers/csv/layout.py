"""Where a CSV's data start and how its lines split, found from the file's first 64 KiB.

:func:`sniff` looks at the head of the file only (the data are then parsed by pyarrow):

- **text**: a regular file, UTF-8 (a byte-order mark is skipped; a header in Latin-1 is read as
  such), no NUL byte, line ends LF, CRLF or CR;
- **delimiter** (``auto``): the candidate among ``,`` ``;`` tab and runs of blanks that splits the
  last half of the head's lines into one number of fields (90 % of them) with the most numeric
  cells, then the most fields; with ``;``, tab or blanks, numbers written with a decimal comma
  (``1,5``) make the decimal point ``,``;
- **metadata lines before the header** (``Fs,100``, a logger's name): the data are the block of
  data-like lines (the data's number of fields, mostly numbers) running to the end of the head,
  with the header line just above them; the lines before it are skipped (``skip_rows`` says
  how many instead); a rate line among them (``Fs``, ``rate``, ``sample rate``, ``ODR`` ...)
  gives the sample rate;
- **header**: the block's first line when most of its cells are not numbers (``header`` says
  so instead); names are stripped of blanks and quotes;
- **a trailing delimiter** on every data line (``1,2,3,``) is an empty last column, unnamed when
  the header has no delimiter at its end;
- a tab-separated file whose header is separated by spaces is read as blank-separated.

:func:`line_of_row` and :func:`line_with_fields` turn a parser's row number or field-count
complaint into a file line number, for error messages (they read the file; errors only).
"""

from __future__ import annotations

import csv
import os
import re
import stat
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from imupipe.readers.errors import ReadError

HEAD_BYTES = 1 << 16
"""How much of the file's start is looked at to find the delimiter, the header and metadata."""

NUMBER = re.compile(
    r"^\s*[-+]?(\d+\.?\d*([eE][-+]?\d+)?|\.\d+([eE][-+]?\d+)?|nan|inf|infinity)\s*$", re.I
)
"""A number as pyarrow's float parser takes it (blanks around it allowed)."""
COMMA_NUMBER = re.compile(r"^\s*[-+]?(\d+,\d*|,\d+)([eE][-+]?\d+)?\s*$")
"""A number written with a decimal comma (``1,5``, ``-0,25e-3``)."""
_RATE_KEY = re.compile(
    r"^(fs|rate|odr|frequency|sample[ _-]?rate|sampling[ _-]?(rate|frequency))"
    r"\s*(\(hz\)|\[hz\]|hz)?$",
    re.IGNORECASE,
)
_LINE_END = re.compile(rb"\r\n|\n|\r")
_BOMS = {b"\xff\xfe": "UTF-16", b"\xfe\xff": "UTF-16", b"\x00\x00\xfe\xff": "UTF-32"}
DELIMITERS = {",": ",", ";": ";", "\t": "\t", "\\t": "\t", "tab": "\t", "whitespace": "whitespace"}
"""The ``delimiter`` key's values and the delimiter each means (``auto``: sniffed)."""


@dataclass
class Layout:
    """How to read one CSV file.

    The data rows start at byte ``data_offset`` (line ``first_line``, 1-based) and split into
    ``fields`` fields by ``delimiter`` (``whitespace``: runs of blanks), with ``decimal`` as the
    decimal point; ``names`` are the header's column names (empty without a header, where columns
    are named by their 0-based index); ``skipped`` the text of the lines skipped before the
    header; ``rate_hz`` a sample rate read from one of them; ``clean``: the file needs the
    in-memory pass that removes comment and blank lines and turns runs of blanks into commas."""

    delimiter: str
    decimal: str
    header: bool
    names: list[str]
    fields: int
    data_offset: int
    first_line: int
    header_line: int = 0
    skipped: list[str] = field(default_factory=list)
    rate_hz: float | None = None
    clean: bool = False


@dataclass
class _Line:
    index: int
    """0-based line number in the file."""
    text: str
    start: int
    """Byte offset of the line's first character."""


def cells(text: str, delimiter: str) -> list[str]:
    """The fields of one line (quotes honoured; ``whitespace``: runs of blanks)."""
    if delimiter == "whitespace":
        return text.split()
    return next(csv.reader([text], delimiter=delimiter), [])


def is_number(cell: str, decimal: str = ".") -> bool:
    """:data:`NUMBER`, or with ``decimal`` "," :data:`COMMA_NUMBER`, matches ``cell``.

    Counted first: :data:`NUMBER` takes no comma and :data:`COMMA_NUMBER` exactly one, so a
    cell with commas (a whole line, as the sniff splits it by another delimiter) is refused
    without the expressions' backtracking over its digits (the sniff of a 7-column CSV's
    64 KiB: 0.05 s -> 0.01 s, issue 39); the same answer for every cell."""
    commas = cell.count(",")
    if not commas:
        return NUMBER.match(cell) is not None
    return decimal == "," and commas == 1 and COMMA_NUMBER.match(cell) is not None


def _head(path: Path) -> tuple[bytes, bool]:
    """The file's first bytes and whether there is more; ReadError for what is not a text file."""
    try:
        mode = os.stat(path).st_mode
        if not stat.S_ISREG(mode):
            raise ReadError(f"{path}: not a regular file (a device, pipe or folder): not a CSV")
        with open(path, "rb") as fh:
            head = fh.read(HEAD_BYTES + 1)
    except OSError as exc:
        raise ReadError(f"{path}: cannot read: {exc.strerror or exc}") from None
    more = len(head) > HEAD_BYTES
    head = head[:HEAD_BYTES]
    for bom, name in _BOMS.items():
        if head.startswith(bom):
            raise ReadError(f"{path}: {name} text; save the file as UTF-8 (or ASCII)")
    nul = head.find(b"\x00")
    if nul >= 0:
        raise ReadError(f"{path}: not a text file (NUL byte at byte {nul}): not a CSV")
    return head, more


def _decode(raw: bytes) -> str:
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def _lines(path: Path, head: bytes, more: bool) -> list[_Line]:
    """Every line of the head (the last one dropped when the head cuts it)."""
    bom = 3 if head.startswith(b"\xef\xbb\xbf") else 0
    out: list[_Line] = []
    start = bom
    for m in _LINE_END.finditer(head, bom):
        out.append(_Line(len(out), _decode(head[start : m.start()]), start))
        start = m.end()
    if start < len(head):
        if more:
            if not out:
                raise ReadError(
                    f"{path}: no line break in the first {HEAD_BYTES // 1024} KiB: not a CSV"
                )
        else:
            out.append(_Line(len(out), _decode(head[start:]), start))
    return out


def _is_comment(text: str, comment: str | None) -> bool:
    return bool(comment) and text.lstrip().startswith(comment)  # type: ignore[arg-type]


@dataclass
class _Split:
    delimiter: str
    decimal: str
    fields: int
    """Fields of a data line."""
    empty_last: bool
    """The data lines' last field is empty (perhaps a trailing delimiter)."""
    numeric: float

    def count(self, text: str) -> int:
        return len(cells(text, self.delimiter))

    def header_like(self, text: str) -> bool:
        """The data's number of fields, or one fewer when the data end with a delimiter."""
        n = self.count(text)
        return n == self.fields or (self.empty_last and n == self.fields - 1)

    def data_like(self, text: str) -> bool:
        """The data's number of fields, and at least as many numbers as other cells."""
        c = cells(text, self.delimiter)
        if len(c) != self.fields:
            return False
        filled = [x for x in c if x.strip()]
        numbers = sum(is_number(x, self.decimal) for x in filled)
        return numbers >= len(filled) - numbers


def _split_rule(texts: list[str], delimiter: str, decimal: str) -> _Split:
    """The delimiter and decimal point that split ``texts`` (the head's last lines) best."""
    tail = texts[len(texts) // 2 :] or texts
    candidates = [",", ";", "\t", "whitespace"] if delimiter == "auto" else [DELIMITERS[delimiter]]
    best: tuple[tuple, _Split] | None = None
    for cand in candidates:
        decimals = [decimal] if decimal != "auto" else ([".", ","] if cand != "," else ["."])
        split = [cells(t, cand) for t in tail]
        counts = [len(c) for c in split]
        every = [len(cells(t, cand)) for t in texts] if len(tail) < 20 else counts
        mode = max(set(counts), key=lambda k: (counts.count(k), every.count(k)))
        share = counts.count(mode) / len(counts)
        data = [c for c in split if len(c) == mode]
        empty_last = mode > 1 and all(not c[-1].strip() for c in data)
        for dec in decimals:
            values = [x for c in data for x in c if x.strip()]
            numeric = sum(is_number(x, dec) for x in values) / max(len(values), 1)
            score = (mode > 1, share >= 0.9, numeric, mode, dec == ".")
            if best is None or score > best[0]:
                best = (score, _Split(cand, dec, mode, empty_last, numeric))
    assert best is not None
    return best[1]


def _rate(lines: list[str]) -> float | None:
    rate = None
    for line in lines:
        key, _, value = line.replace("\t", ",").replace(":", ",").replace("=", ",").partition(",")
        value = value.strip().strip(",").strip()
        if _RATE_KEY.match(key.strip()) and NUMBER.match(value) and 0 < float(value) < 1e12:
            rate = float(value)
    return rate


def sniff(
    path: Path,
    *,
    delimiter: str = "auto",
    decimal: str = "auto",
    header: bool | None = None,
    skip_rows: int | None = None,
    comment: str | None = None,
) -> Layout:
    """The layout of the CSV file ``path`` (see the module docstring)."""
    if delimiter not in DELIMITERS and delimiter != "auto":
        raise ReadError(
            f"{path}: csv.delimiter = {delimiter!r} is not one of auto, ',', ';', '\\t', whitespace"
        )
    if decimal not in ("auto", ".", ","):
        raise ReadError(f"{path}: csv.decimal = {decimal!r} is not one of auto, '.', ','")
    if skip_rows is not None and skip_rows < 0:
        raise ReadError(f"{path}: csv.skip_rows must be >= 0")
    head, more = _head(path)
    every = _lines(path, head, more)
    lines = [ln for ln in every if ln.text.strip() and not _is_comment(ln.text, comment)]
    if not lines:
        raise ReadError(f"{path}: the file is empty" + (" (only comment lines)" if every else ""))
    rule = _split_rule([ln.text for ln in lines], delimiter, decimal)
    if skip_rows is not None:
        start = next((k for k, ln in enumerate(lines) if ln.index >= skip_rows), len(lines))
        if start >= len(lines):
            raise ReadError(f"{path}: no data lines after the {skip_rows} lines skipped")
        has_header = header if header is not None else not rule.data_like(lines[start].text)
    else:
        start = len(lines)
        while start > 0 and not rule.data_like(lines[start - 1].text):
            start -= 1  # a footer or commented-out lines after the data: the parser names them
        start = start or len(lines)
        while start > 0 and (
            rule.data_like(lines[start - 1].text)
            or (  # a malformed line between data lines: the parser names it
                start > 1
                and rule.data_like(lines[start - 2].text)
                and not rule.header_like(lines[start - 1].text)
            )
        ):
            start -= 1
        if start == len(lines):  # nothing data-like: the last block of lines with equal fields
            while start > 0 and rule.header_like(lines[start - 1].text):
                start -= 1
            start = min(start, len(lines) - 1)
            has_header = header is not False
        elif header is None:
            has_header = start > 0 and rule.header_like(lines[start - 1].text)
            if not has_header and start > 0 and rule.delimiter == "\t":
                above = lines[start - 1].text.split()
                data = [ln.text for ln in lines[start:]]
                if len(above) == rule.fields and all(len(t.split()) == rule.fields for t in data):
                    rule = _Split("whitespace", rule.decimal, rule.fields, False, rule.numeric)
                    has_header = True
            start -= has_header
        else:
            has_header = header
            start -= header and start > 0
    head_line = lines[start]
    names: list[str] = []
    data = start
    if has_header:
        names = [c.strip().strip('"').strip() for c in cells(head_line.text, rule.delimiter)]
        data = start + 1
    if data >= len(lines):
        if more:
            raise ReadError(f"{path}: no data lines in the first {HEAD_BYTES // 1024} KiB")
        raise ReadError(
            f"{path}: the file has a header but no rows" if has_header else f"{path}: no data lines"
        )
    first_data = lines[data]
    blank_with_spaces = any(not ln.text.strip() and ln.text for ln in every[head_line.index :])
    return Layout(
        delimiter=rule.delimiter,
        decimal=rule.decimal,
        header=bool(has_header),
        names=names,
        fields=rule.fields,
        data_offset=first_data.start,
        first_line=first_data.index + 1,
        header_line=head_line.index + 1,
        skipped=[ln.text.strip() for ln in lines[:start]],
        rate_hz=_rate([ln.text.strip() for ln in lines[:start]]),
        clean=rule.delimiter == "whitespace" or bool(comment) or blank_with_spaces,
    )


def data_lines(path: Path, layout: Layout, comment: str | None) -> Iterator[tuple[int, str]]:
    """(1-based file line, text) of every data line, as the parser sees them (blank and comment
    lines left out). Reads the file in Python: for error messages only."""
    with open(path, "rb") as fh:
        fh.seek(layout.data_offset)
        text = fh.read()
    number = layout.first_line
    pos = 0
    for m in [*_LINE_END.finditer(text), None]:
        end = m.start() if m else len(text)
        if m is None and end == pos:
            break
        line = _decode(text[pos:end])
        if line.strip() and not _is_comment(line, comment):
            yield number, line
        number += 1
        if m is None:
            break
        pos = m.end()


def line_of_row(path: Path, layout: Layout, comment: str | None, row: int) -> int | None:
    """The file line of data row ``row`` (0-based), or None past the end."""
    for k, (number, _text) in enumerate(data_lines(path, layout, comment)):
        if k == row:
            return number
    return None


def line_with_fields(
    path: Path, layout: Layout, comment: str | None
) -> tuple[int, int, str] | None:
    """(file line, fields, text) of the first data line whose number of fields is not the
    layout's."""
    for number, text in data_lines(path, layout, comment):
        n = len(cells(text, layout.delimiter))
        if n != layout.fields:
            return number, n, text
    return None
