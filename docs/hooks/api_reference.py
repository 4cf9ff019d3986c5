"""mkdocs hook: the Python API reference, generated from the docstrings.

A page line ``<!-- api: NAME NAME ... -->`` is followed, up to ``<!-- /api -->``, by each public
name of ``imupipe``'s signature (with the type hints as written) and its docstring, written into
the page itself (``python docs/hooks/api_reference.py``; ``tests/test_docs_reference.py`` fails
while the page is stale), so that it reads on GitHub as on the site; a class also gets its public
methods and properties. The reference cannot drift from the code: a keyword added to a stage's
``Options`` appears in ``imupipe.<stage>``'s signature here (through ``imupipe/_stages.py``,
which the tests keep equal to what ``imupipe._codegen`` writes). A name not in
``imupipe.__all__`` is an error, as is a public name left off the page (the build is strict).
"""

from __future__ import annotations

import dataclasses
import inspect
import re
from pathlib import Path
from typing import Any

import imupipe

MARKER = re.compile(r"^<!-- api: ([\w ]+) -->$", re.MULTILINE)
END = "<!-- /api -->"
BLOCK = re.compile(r"^<!-- api: ([\w ]+) -->$(?:.*?^<!-- /api -->$)?", re.MULTILINE | re.DOTALL)
"""A marker and what was generated after it (up to :data:`END`), or a marker alone."""
PAGE = Path(__file__).resolve().parents[1] / "reference" / "python-api.md"
ROLE = re.compile(r":(?:func|class|data|attr|meth|mod):`~?([^`]+)`")
WIDTH = 96


def _doc(obj: Any) -> str:
    """The docstring as markdown: Sphinx roles become code spans (``~a.b.c`` -> ``c``)."""
    text = inspect.getdoc(obj) or ""
    return ROLE.sub(lambda m: f"``{m.group(1).rsplit('.', 1)[-1]}``", text)


def _param(p: inspect.Parameter, factories: dict[str, Any]) -> str:
    text = p.name if p.kind is not p.VAR_KEYWORD else f"**{p.name}"
    if p.name in factories:  # a dataclass field's default_factory: its value
        p = p.replace(default=factories[p.name]())
    if p.annotation is not p.empty:
        text += f": {p.annotation if isinstance(p.annotation, str) else inspect.formatannotation(p.annotation)}"
    if p.default is not p.empty:
        text += f" = {p.default!r}" if not isinstance(p.default, str) else f' = "{p.default}"'
    return text


def signature(name: str, obj: Any) -> str:
    """``name(params) -> return``, one parameter a line when it does not fit on one."""
    sig = inspect.signature(obj)
    factories = {}
    if dataclasses.is_dataclass(obj):
        fields = dataclasses.fields(obj)
        factories = {
            f.name: f.default_factory
            for f in fields
            if f.default_factory is not dataclasses.MISSING
        }
    params, starred = [], False
    for p in sig.parameters.values():
        if p.name == "self" or p.name == "cls":
            continue
        if p.kind is p.KEYWORD_ONLY and not starred:
            params.append("*")
            starred = True
        params.append(_param(p, factories))
    ret = sig.return_annotation
    tail = (
        ""
        if ret is sig.empty or inspect.isclass(obj)
        else f" -> {ret if isinstance(ret, str) else inspect.formatannotation(ret)}"
    )
    one = f"{name}({', '.join(params)}){tail}"
    if len(one) <= WIDTH:
        return one
    return f"{name}(\n" + "".join(f"    {p},\n" for p in params) + f"){tail}"


def _members(cls: type) -> list[str]:
    out = []
    for key, value in vars(cls).items():
        if key.startswith("_"):
            continue
        if isinstance(value, property):
            out.append(f"#### `{cls.__name__}.{key}`\n\n(property) {_doc(value)}\n")
        elif isinstance(value, classmethod | staticmethod) or inspect.isfunction(value):
            func = value.__func__ if isinstance(value, classmethod | staticmethod) else value
            sig = signature(f"{cls.__name__}.{key}", func)
            out.append(f"#### `{cls.__name__}.{key}`\n\n```python\n{sig}\n```\n\n{_doc(func)}\n")
    return out


def entry(name: str) -> str:
    """The reference of ``imupipe.<name>``."""
    if name not in imupipe.__all__:
        raise ValueError(f"<!-- api: {name} -->: not a public name of imupipe (see __all__)")
    obj = getattr(imupipe, name)
    head = f"### `imupipe.{name}`\n\n"
    if inspect.isclass(obj) and issubclass(obj, BaseException):
        return head + f"{_doc(obj)}\n"
    sig = signature(f"imupipe.{name}", obj)
    parts = [head + f"```python\n{sig}\n```\n\n{_doc(obj)}\n"]
    if inspect.isclass(obj):
        parts += _members(obj)
    return "\n".join(parts)


def render(markdown: str) -> str:
    """``markdown`` with each marker's entries written after it, up to its end marker ``<!--
    /api -->`` (what was there replaced: the page in the repository holds the reference, so it
    reads on GitHub too; ``python docs/hooks/api_reference.py`` writes it, a test keeps it
    fresh)."""

    def block(m: re.Match[str]) -> str:
        body = "\n".join(entry(n) for n in m.group(1).split())
        return f"<!-- api: {m.group(1)} -->\n\n{body}\n{END}"

    return BLOCK.sub(block, markdown)


def on_page_markdown(markdown: str, **_: object) -> str:
    return render(markdown)


def on_post_build(**_: object) -> None:
    """Every public name is on the reference page (``__version__`` aside)."""
    page = PAGE
    listed = {
        n for m in MARKER.finditer(page.read_text(encoding="utf-8")) for n in m.group(1).split()
    }
    missing = [n for n in imupipe.__all__ if n not in listed and n != "__version__"]
    if missing:
        raise ValueError(f"{page}: public names of imupipe not documented: {', '.join(missing)}")


if __name__ == "__main__":  # python docs/hooks/api_reference.py: write the page's reference
    PAGE.write_text(render(PAGE.read_text(encoding="utf-8")), encoding="utf-8")
    print(PAGE)
