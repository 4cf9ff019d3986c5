"""What each stage option means, read from the ``Options`` dataclasses themselves.

Every stage declares its config keys as the fields of a nested ``@dataclass Options``, each field
followed by its docstring (the attribute-docstring convention of Sphinx and mkdocstrings). This
module reads them back (name, type, default, docstring) so the config reference in the docs is
generated from the code and cannot drift from it.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
import typing
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class OptionDoc:
    """One config key of a stage: its name, its type as written, its default and its docstring."""

    name: str
    type: str
    default: str
    doc: str


def _docstrings(cls: type) -> dict[str, str]:
    """Field name -> the string literal that follows the field in the class body."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs: dict[str, str] = {}
    for node, after in zip(body, body[1:], strict=False):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(after, ast.Expr)
            and isinstance(after.value, ast.Constant)
            and isinstance(after.value.value, str)
        ):
            docs[node.target.id] = inspect.cleandoc(after.value.value)
    return docs


def _type_text(hint: Any) -> str:
    origin = typing.get_origin(hint)
    if origin is typing.Literal:
        return " | ".join(repr(a) for a in typing.get_args(hint))
    text = getattr(hint, "__name__", None) if origin is None else None
    return text or str(hint).replace("typing.", "")


def _default_text(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
    else:
        return "(required)"
    if value is None:
        return "(none)"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    return repr(value)


def option_docs(options_cls: type) -> list[OptionDoc]:
    """The documented config keys of an ``Options`` dataclass, in declaration order."""
    hints = typing.get_type_hints(options_cls)
    docs: dict[str, str] = {}
    for base in reversed(options_cls.__mro__):  # fields inherited from a base dataclass too
        if dataclasses.is_dataclass(base):
            docs.update(_docstrings(base))
    return [
        OptionDoc(f.name, _type_text(hints[f.name]), _default_text(f), docs.get(f.name, ""))
        for f in dataclasses.fields(options_cls)
    ]
