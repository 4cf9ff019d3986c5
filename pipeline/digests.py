"""SHA-1 and SHA-256 digests without importing :mod:`hashlib` (issue 39: a command's fixed cost).

``hashlib`` loads OpenSSL's ``libcrypto`` through ``_hashlib`` on import: 3.4-9 ms of CPU on
every command that hashes anything (a ``convert`` hashes its calibration chain and read settings,
and names its temporary files after a hash of the host name), a twentieth of a one-log
``convert``'s own cost. CPython's own implementations of the same functions (FIPS 180-4; the
modules ``hashlib`` falls back to without OpenSSL: ``_sha1``, and ``_sha256`` up to Python 3.11,
``_sha2`` from 3.12) load in about 0.2 ms and give the same digests (tested against ``hashlib``
in ``tests/test_cli_startup.py``); ``hashlib`` is used where they are missing."""

from __future__ import annotations

try:
    from _sha2 import sha256 as _sha256  # Python 3.12+
except ImportError:
    try:
        from _sha256 import sha256 as _sha256  # Python 3.11
    except ImportError:  # a Python built without them
        from hashlib import sha256 as _sha256
try:
    from _sha1 import sha1 as _sha1
except ImportError:  # a Python built without it
    from hashlib import sha1 as _sha1


def sha256_hex(data: bytes) -> str:
    """The SHA-256 digest of ``data``, as 64 lowercase hex digits (``hashlib.sha256``'s)."""
    return _sha256(data).hexdigest()


def sha1_hex(data: bytes) -> str:
    """The SHA-1 digest of ``data``, as 40 lowercase hex digits (``hashlib.sha1``'s)."""
    return _sha1(data).hexdigest()
