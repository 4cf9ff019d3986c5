"""The optional compiled helpers of the readers (everything else is in pyproject.toml).

Four C sources, CPython API and buffer protocol only, each the compiled twin of a numpy or
pure-Python path that gives the same bytes:

- ``imupipe.readers._records`` (``readers/_records.c``): the sequential ULog and DataFlash record
  walks, the copy of fixed-size payloads and the split of ULog format records; fallback
  ``imupipe.readers.record_walk`` (the format split: ``imupipe.readers.ulog.records._format``);
- ``imupipe.readers._chunks`` (``readers/_chunks.c``): one MCAP chunk's CDR sensor messages
  checked and copied into the table's columns, and its CRC-32 by carry-less multiplication;
  fallback ``imupipe.readers.chunk_fill``'s numpy path and ``zlib.crc32``;
- ``imupipe.readers._jsonscan`` (``readers/_jsonscan.c``): a JSON channel's messages checked
  against a template and their mapped numbers parsed as ``float()`` / ``int()`` parse them;
  fallback ``imupipe.readers.json_numbers``'s numpy path;
- ``imupipe.readers._protoscan`` (``readers/_protoscan.c``): a protobuf channel's messages walked
  tag by tag, once each, and their mapped fields written into the columns; fallback
  ``imupipe.readers.message_fields``' numpy scan.

``pip install .`` / ``pip install -e .`` build them when a C compiler is there; ``optional=True``
lets the install go on without one (setuptools prints the compiler's error and skips the
extension). ``IMUPIPE_PURE_PYTHON=1`` forces the fallbacks. For a source checkout used in
place: ``python setup.py build_ext --inplace`` puts the modules next to the sources in
``readers/``.
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension("imupipe.readers._records", sources=["readers/_records.c"], optional=True),
        Extension("imupipe.readers._chunks", sources=["readers/_chunks.c"], optional=True),
        Extension("imupipe.readers._jsonscan", sources=["readers/_jsonscan.c"], optional=True),
        Extension("imupipe.readers._protoscan", sources=["readers/_protoscan.c"], optional=True),
    ]
)
