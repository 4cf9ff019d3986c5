"""scipy.special's ``gammaincinv``, ``digamma`` and ``polygamma``, loaded without the package's
``__init__``.

The ``allan`` stage's chi-square bounds (``2 * gammaincinv(edf / 2, p)``, Greenhall and Riley,
"Uncertainty of stability variances based on finite differences", PTTI 2003) and its fit's
log-variance moments (digamma and trigamma of ``edf / 2``) need these three functions, whose
values its outputs hold to the last bit. ``import scipy.special`` (scipy 1.17) costs 0.33-0.43 s
of CPU, of which the compiled ufuncs are about 0.03 s: the rest is its array-API layer, whose
vendored ``array_api_compat`` clones numpy's namespace (``hasattr`` on every name numpy lists),
which imports numpy's lazy ``f2py``, ``testing``, ``random``, ``fft``, ``polynomial`` and
``ma`` (measured on the whole ``imupipe run`` with one ``allan`` stage, issue 39).

So the two modules that define them, ``scipy.special._ufuncs`` (the ufuncs ``gammaincinv`` and
``psi``, whose alias ``digamma`` is) and ``scipy.special._basic`` (``polygamma``), are imported
under a stand-in for the package: the package's own module object, made from its spec and not
executed, in ``sys.modules`` only while they load, with the package's import lock held (a thread
importing ``scipy.special`` meanwhile waits, then imports it whole). The functions are the very
objects ``scipy.special`` exports (with ``SCIPY_ARRAY_API`` unset; else its wrappers call them
for numpy arrays), so every value is the same.

Afterwards nothing is left in a state a normal import would not reach: a later
``import scipy.special`` (by the user, scipy.stats, ...) runs the package's ``__init__`` as usual
and finds these submodules imported, and a one-shot meta path finder (:class:`_BindLoaded`)
binds them to the package as attributes, as an import of them inside it would have. When
``scipy.special`` is already imported, or this Python lacks the import lock used
(``importlib._bootstrap._ModuleLockManager``, CPython 3.3+), it is imported the usual way.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.machinery
import importlib.util
import sys
from collections.abc import Callable, Sequence
from types import ModuleType
from typing import Any

PACKAGE = "scipy.special"
SUBMODULES = ("_ufuncs", "_basic")


class _BindLoaded:
    """A meta path finder, removed at its first use: when ``scipy.special`` is imported for real,
    its submodules imported before (``loaded``: name -> module) become attributes of it before
    its ``__init__`` runs, as importing them from inside the package would have made them."""

    def __init__(self, loaded: dict[str, ModuleType]) -> None:
        self.loaded = loaded

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> Any:
        if fullname != PACKAGE:
            return None
        with contextlib.suppress(ValueError):
            sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec  # None: the finders after this one find it
        exec_module = spec.loader.exec_module
        loaded = self.loaded

        def exec_and_bind(module: ModuleType) -> None:
            for name, sub in loaded.items():
                setattr(module, name.rpartition(".")[2], sub)
            exec_module(module)

        spec.loader.exec_module = exec_and_bind  # type: ignore[method-assign]
        return spec


def _import_usual() -> list[ModuleType]:
    return [importlib.import_module(f"{PACKAGE}.{name}") for name in SUBMODULES]


def load() -> list[ModuleType]:
    """The modules :data:`SUBMODULES` of :data:`PACKAGE`, imported without running the
    package's ``__init__`` when it is not imported yet (see the module's docstring)."""
    bootstrap = getattr(importlib, "_bootstrap", None)
    lock = getattr(bootstrap, "_ModuleLockManager", None)
    if PACKAGE in sys.modules or lock is None:
        return _import_usual()
    spec = importlib.util.find_spec(PACKAGE)  # imports the parent package (scipy: light)
    if spec is None or spec.submodule_search_locations is None:
        return _import_usual()
    with lock(PACKAGE):  # another thread's ``import scipy.special`` waits here
        if PACKAGE in sys.modules:
            return _import_usual()
        before = set(sys.modules)
        stand_in = importlib.util.module_from_spec(spec)  # its __path__; not executed
        spec._initializing = True  # type: ignore[attr-defined] # another importer waits
        sys.modules[PACKAGE] = stand_in
        try:
            modules = _import_usual()
        finally:
            if sys.modules.get(PACKAGE) is stand_in:
                del sys.modules[PACKAGE]
            spec._initializing = False  # type: ignore[attr-defined]
        loaded = {
            name: sys.modules[name]
            for name in sorted(set(sys.modules) - before)
            if name.startswith(PACKAGE + ".") and name.count(".") == PACKAGE.count(".") + 1
        }
        sys.meta_path.insert(0, _BindLoaded(loaded))
    return modules


_ufuncs, _basic = load()

gammaincinv: Callable[..., Any] = _ufuncs.gammaincinv
"""Inverse of the regularised lower incomplete gamma function (scipy.special.gammaincinv)."""
digamma: Callable[..., Any] = _ufuncs.psi
"""The digamma function (scipy.special.digamma, an alias of psi)."""
polygamma: Callable[..., Any] = _basic.polygamma
"""The polygamma function (scipy.special.polygamma; ``polygamma(1, x)``: trigamma)."""
