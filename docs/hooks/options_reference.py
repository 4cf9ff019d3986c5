"""mkdocs hook: the config-key tables of the reference, generated from the code.

A page line ``<!-- options: STAGE_TYPE -->`` becomes the table of that stage's keys (name, type,
default, meaning) read from its ``Options`` dataclass and the field docstrings;
``<!-- options: csv -->`` does the same for the ``[inputs.NAME.csv]`` mapping. The tables cannot
drift from the code: a key added to a stage appears here with its docstring.
"""

from __future__ import annotations

import re

from imupipe.readers.spec import CsvMapping
from imupipe.stages.options_doc import option_docs
from imupipe.stages.registry import stage_class

MARKER = re.compile(r"^<!-- options: ([a-z_]+) -->$", re.MULTILINE)
HIDDEN = {"required"}  # set by the config parser, not a user key


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def options_table(name: str) -> str:
    cls = CsvMapping if name == "csv" else stage_class(name).Options
    rows = ["| key | type | default | meaning |", "|---|---|---|---|"]
    for opt in option_docs(cls):
        if opt.name in HIDDEN:
            continue
        kind = " ".join(opt.type.split()).replace(" | ", " or ")
        rows.append(f"| `{opt.name}` | {kind} | `{_cell(opt.default)}` | {_cell(opt.doc)} |")
    return "\n".join(rows)


def on_page_markdown(markdown: str, **_: object) -> str:
    return MARKER.sub(lambda m: options_table(m.group(1)), markdown)
