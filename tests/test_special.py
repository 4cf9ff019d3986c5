"""Issue 39: the Allan stage's three scipy.special functions are loaded without the package's
``__init__`` (:mod:`imupipe.stages.special`): the very objects ``scipy.special`` exports, none of
its array-API layer imported, and a later ``import scipy.special`` whole and as usual."""

from __future__ import annotations

import json
import subprocess
import sys

PROBE = """
import json, sys
import imupipe.stages.special as sp
light = sorted(m for m in sys.modules
               if m == "scipy.special" or "array_api_compat" in m or m.startswith("numpy.f2py"))
import scipy.special, scipy.stats
loaded = [m for m in sys.modules if m.startswith("scipy.special._") and m.count(".") == 2]
print(json.dumps({
    "light": light,
    "same": [sp.gammaincinv is scipy.special.gammaincinv, sp.digamma is scipy.special.digamma,
             sp.polygamma is scipy.special.polygamma],
    "unbound": [m for m in loaded if getattr(scipy.special, m.rpartition(".")[2], None)
                is not sys.modules[m]],
    "finders": [type(f).__name__ for f in sys.meta_path if type(f).__name__ == "_BindLoaded"],
    "chi2": float(scipy.stats.chi2.ppf(0.8415, 7.5)),
    "ours": float(2 * sp.gammaincinv(3.75, 0.8415)),
}))
"""


def _probe(code: str) -> dict:
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_loaded_without_the_array_api_layer_then_imported_whole():
    got = _probe(PROBE)
    assert got["light"] == []  # neither the package's __init__ nor what it pulls in
    assert got["same"] == [True, True, True]  # the objects scipy.special exports: same values
    assert got["unbound"] == []  # every submodule loaded early is an attribute of the package
    assert got["finders"] == []  # the one-shot finder is gone
    assert got["ours"] == got["chi2"]


def test_imported_the_usual_way_when_scipy_special_is_there():
    got = _probe("import scipy.special\n" + PROBE.replace('"light": light,', '"light": [],'))
    assert got["same"] == [True, True, True] and got["unbound"] == []
    assert got["finders"] == []
