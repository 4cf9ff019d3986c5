"""The accuracy sweep's families (issue 25): each module exposes ``FAMILY: str`` and
``run(quick: bool) -> list[dict]``, one row per case, with default stage options throughout.

A row: ``family``, ``case`` (short description), ``outcome`` ("answer" or "refused"),
``verdict`` (one of :data:`VERDICTS`), ``error`` (str with unit, against the truth), ``stated``
(str: the stage's stated 95 % uncertainty), ``covered`` (True/False/None: the truth inside the
stated 95 % interval; None where the stage states none).

Verdicts: an answer is ``within tolerance`` when its error against the truth is within the
tolerance the stage states (each family says which), else ``wrong answer``; a refusal is a
``right-cause refusal`` when its message names the case's true cause (each case lists the causes
it may be refused for, as regular expressions, and what to record instead is in every such
message), else ``wrong-cause refusal``. :func:`judge` does this once for every family.
"""

from __future__ import annotations

import importlib
import pkgutil
import re
from collections.abc import Callable, Sequence
from types import ModuleType
from typing import Any

VERDICTS = ("within tolerance", "right-cause refusal", "wrong answer", "wrong-cause refusal")
WRONG = ("wrong answer", "wrong-cause refusal")


def modules() -> list[ModuleType]:
    """Every family module of this package, in name order."""
    return [
        importlib.import_module(f"{__name__}.{m.name}")
        for m in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name)
    ]


def judge(
    family: str,
    case: str,
    attempt: Callable[[], dict[str, Any]],
    causes: Sequence[str] = (),
    refusals: tuple[type[BaseException], ...] = (Exception,),
) -> dict[str, Any]:
    """One row: run ``attempt`` (returns ``{"ok": bool, "error": str, "stated": str,
    "covered": bool | None}`` for an answer); a raised ``refusals`` exception is a refusal, of
    the right cause when its message matches one of ``causes`` (regular expressions)."""
    try:
        got = attempt()
    except refusals as exc:
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        right = any(re.search(c, message) for c in causes)
        return {
            "family": family,
            "case": case,
            "outcome": "refused",
            "verdict": "right-cause refusal" if right else "wrong-cause refusal",
            "error": _short(message),
            "stated": "",
            "covered": None,
        }
    return {
        "family": family,
        "case": case,
        "outcome": "answer",
        "verdict": "within tolerance" if got["ok"] else "wrong answer",
        "error": got["error"],
        "stated": got["stated"],
        "covered": got["covered"],
    }


def _short(message: str, limit: int = 160) -> str:
    """A refusal's message without the stage prefix, cut to ``limit`` characters."""
    message = re.sub(r"^stage '[^']*' on input '[^']*': ", "", message)
    return message if len(message) <= limit else message[: limit - 3] + "..."
