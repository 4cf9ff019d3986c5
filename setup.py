"""The optional compiled helper of the flight-log readers (everything else is in pyproject.toml).

``imupipe.readers._records`` (``readers/_records.c``: the sequential ULog record walk and the
copy of fixed-size payloads, CPython API only) is built by ``pip install .`` / ``pip install -e
.`` when a C compiler is there; ``optional=True`` lets the install go on without it (setuptools
prints the compiler's error and skips the extension), and the readers then use the pure-Python
walks of ``imupipe.readers.record_walk``, which give the same bytes. For a source checkout used
in place: ``python setup.py build_ext --inplace`` puts the module next to the sources in
``readers/``.
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "imupipe.readers._records",
            sources=["readers/_records.c"],
            optional=True,
        ),
        Extension("imupipe.readers._chunks", sources=["readers/_chunks.c"], optional=True),
        Extension("imupipe.readers._jsonscan", sources=["readers/_jsonscan.c"], optional=True),
    ]
)
