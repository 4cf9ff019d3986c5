"""mkdocs hook: the config-key tables of the reference, generated from the code.

A page line ``<!-- options: STAGE_TYPE -->`` becomes the table of that stage's keys (name, type,
default, meaning) read from its ``Options`` dataclass and the field docstrings;
``<!-- options: csv -->`` does the same for the ``[inputs.NAME.csv]`` mapping, and
``<!-- options: fields -->`` for ``[inputs.NAME.fields]``. The tables cannot
drift from the code: a key added to a stage appears here with its docstring.
"""

from __future__ import annotations

import ast
import json
import re
import types
import typing
from typing import Any

from imupipe.readers.spec import CsvMapping, FieldMapping
from imupipe.stages.options_doc import option_docs
from imupipe.stages.registry import stage_class

MARKER = re.compile(r"^<!-- options: ([a-z_]+) -->$", re.MULTILINE)
HIDDEN = {"required"}  # set by the config parser, not a user key
ROLE = re.compile(r":(?:func|class|data|attr|meth|mod):`~?([^`]+)`")


def options_class(name: str) -> type:
    """The dataclass whose fields are the keys of ``name`` (a stage type, ``csv`` or
    ``fields``)."""
    if name == "fields":
        return FieldMapping
    return CsvMapping if name == "csv" else stage_class(name).Options


def type_text(hint: Any) -> str:
    """A type as a reader of TOML sees it: ``"auto" or bool``, ``list of float or none``."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin is typing.Literal:
        return " or ".join(f'"{a}"' if isinstance(a, str) else repr(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(type_text(a) for a in args)
    if hint is type(None):
        return "none"
    if origin is list:
        if not args:
            return "list"
        inner = type_text(args[0])
        return f"list of ({inner})" if " or " in inner else f"list of {inner}"
    if origin is dict:
        return "table" if not args or args[1] is Any else f"table of {type_text(args[1])}"
    if hint is Any:
        return "any"
    if hint is dict:
        return "table"
    return {"str": "string", "float": "float", "int": "integer", "bool": "bool"}.get(
        getattr(hint, "__name__", ""), str(hint)
    )


def default_text(default: str) -> str:
    """An option's default (as ``option_docs`` gives it) as it would be written in TOML."""
    if default == "(none)":
        return "none"
    if default == "(required)":
        return default
    if default[:1] in "[{":  # Python's repr of a list or table: TOML's quotes
        default = json.dumps(ast.literal_eval(default))
    return f"`{_cell(default)}`"


def _cell(text: str) -> str:
    text = ROLE.sub(lambda m: f"``{m.group(1).rsplit('.', 1)[-1]}``", text)
    return " ".join(text.split()).replace("|", "\\|")


def options_table(name: str) -> str:
    cls = options_class(name)
    hints = typing.get_type_hints(cls)
    rows = ["| key | type | default | meaning |", "|---|---|---|---|"]
    for opt in option_docs(cls):
        if opt.name in HIDDEN:
            continue
        rows.append(
            f"| `{opt.name}` | {type_text(hints[opt.name])} | {default_text(opt.default)} "
            f"| {_cell(opt.doc)} |"
        )
    return "\n".join(rows)


def on_page_markdown(markdown: str, **_: object) -> str:
    return MARKER.sub(lambda m: options_table(m.group(1)), markdown)
