"""The reference cannot drift from the code, and shipped text carries no internal words.

- Every config key of every registered stage (its ``Options`` dataclass) and of the CSV mapping
  has a docstring: the generated tables of ``docs/reference`` never show an empty meaning.
- Every stage type has its generated table in ``docs/reference/stages.md``.
- The hand-written tables of ``docs/reference/config.md`` list exactly the keys the config parser
  accepts in ``[inputs.NAME]`` and ``[output]``.
- The README, the docs, the examples and the package's source (docstrings, messages, comments)
  cite methods by their papers and patents, never by the project's internal names for the source
  documents.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from imupipe.pipeline.config import INPUT_KEYS, OUTPUT_KEYS
from imupipe.readers.spec import CsvMapping, FieldMapping
from imupipe.stages.options_doc import option_docs
from imupipe.stages.registry import STAGE_TYPES, stage_class

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT / "docs" / "reference"


@pytest.mark.parametrize("name", [*STAGE_TYPES, "csv", "fields"])
def test_every_config_key_has_a_docstring(name: str) -> None:
    cls = {"csv": CsvMapping, "fields": FieldMapping}.get(name) or stage_class(name).Options
    missing = [o.name for o in option_docs(cls) if not o.doc.strip() and o.name != "required"]
    assert not missing, f"{name}: keys without a docstring: {missing}"


def test_every_stage_has_its_generated_table() -> None:
    text = (REFERENCE / "stages.md").read_text(encoding="utf-8")
    for name in STAGE_TYPES:
        assert f"<!-- options: {name} -->" in text, name
        assert f"## `{name}`" in text, name


def _table_keys(page: Path, heading: str) -> set[str]:
    """The first-column keys of the table under ``heading`` on ``page``."""
    text = page.read_text(encoding="utf-8")
    section = text.split(f"\n{heading}\n", 1)[1].split("\n## ", 1)[0]
    return set(re.findall(r"^\| `([a-z_]+)` \|", section, flags=re.MULTILINE))


@pytest.mark.parametrize(
    ("heading", "keys"), [("## `[inputs.NAME]`", INPUT_KEYS), ("## `[output]`", OUTPUT_KEYS)]
)
def test_config_tables_list_every_key(heading: str, keys: set[str]) -> None:
    assert _table_keys(REFERENCE / "config.md", heading) == keys


# -- internal words -----------------------------------------------------------------------------

INTERNAL = re.compile(
    r"\bseeds?[ _-]?0\d\d"  # "seed 000", "seeds 000/004", "seed000"
    r"|\bseeds\b"  # the source documents as a set (random seeds are "seed", "--seed N")
    r"|\bseed (?:document|article|patent)s?\b"
    r"|\bSPEC\b"  # the internal contract ("spec", "InputSpec", readers/spec.py are not it)
    r"|METHODS\.md"
)
SHIPPED = [
    ROOT / "README.md",
    ROOT / "DEVELOPERS.md",
    ROOT / "mkdocs.yml",
    ROOT / "pyproject.toml",
    *sorted((ROOT / "docs").rglob("*.md")),
    *sorted((ROOT / "docs").rglob("*.py")),
    *sorted(p for p in (ROOT / "examples").rglob("*") if p.suffix in {".toml", ".sh", ".md"}),
    *(
        p
        for folder in ("pipeline", "readers", "stages")
        for p in sorted((ROOT / folder).rglob("*.py"))
    ),
]
OWNED_ELSEWHERE: dict[str, str] = {}
"""Pages with internal words that another change removes (strict xfail until it lands)."""


QUOTED_OLD_VALUES = {
    # the value 0.1 accepted, quoted so that users of 0.1 find what it became
    "docs/changes.md": ['model = "seed000"'],
}


def _shipped_ids() -> list[str]:
    return [str(p.relative_to(ROOT)) for p in SHIPPED]


@pytest.mark.parametrize(
    "rel",
    [
        pytest.param(rel, marks=pytest.mark.xfail(strict=True, reason=OWNED_ELSEWHERE[rel]))
        if rel in OWNED_ELSEWHERE
        else rel
        for rel in _shipped_ids()
    ],
)
def test_no_internal_words(rel: str) -> None:
    text = (ROOT / rel).read_text(encoding="utf-8")
    for quoted in QUOTED_OLD_VALUES.get(rel, []):
        text = text.replace(quoted, "")
    found = [
        f"line {text.count(chr(10), 0, m.start()) + 1}: {m.group(0)!r}"
        for m in INTERNAL.finditer(text)
    ]
    assert not found, f"{rel}: " + "; ".join(found)


def test_the_pattern_finds_the_words_and_spares_random_seeds() -> None:
    for text in ("seed 000's ImuDataSum", "seeds 000/004", 'model = "seed000"', "(SPEC)"):
        assert INTERNAL.search(text), text
    for text in ("--seed 4", "random seed", "InputSpec", "readers/spec.py", "a spec"):
        assert not INTERNAL.search(text), text


def test_python_api_page_holds_its_reference_and_is_fresh() -> None:
    """Issue 38: ``docs/reference/python-api.md`` holds the generated reference itself (it reads
    on GitHub, not only on the built site), and it is what the generator writes from today's
    docstrings and signatures (``python docs/hooks/api_reference.py`` after a change)."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "docs" / "hooks" / "api_reference.py"
    spec = importlib.util.spec_from_file_location("api_reference", path)
    assert spec is not None and spec.loader is not None
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    page = hook.PAGE.read_text(encoding="utf-8")
    assert page == hook.render(page), "stale: run python docs/hooks/api_reference.py"
    assert "### `imupipe.read`" in page and "rows: Literal['samples', 'messages']" in page
    assert page.count("<!-- api: ") == page.count(hook.END) >= 5
