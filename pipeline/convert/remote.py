"""Logs and outputs on object storage: ``s3://`` (and the other ``pyarrow.fs`` schemes) for
``imupipe convert``'s inputs, ``--out`` and its manifest, so that a Ray cluster needs no shared
file system.

**Filesystems.** A URL (``scheme://bucket/key``) is opened with :mod:`pyarrow.fs`: ``s3://``
with :class:`pyarrow.fs.S3FileSystem` (credentials from the standard AWS chain: the variables
``AWS_ACCESS_KEY_ID`` / ``AWS_SECRET_ACCESS_KEY`` / ``AWS_SESSION_TOKEN``, ``~/.aws/credentials``
and ``~/.aws/config`` with ``AWS_PROFILE``, an instance role; region from ``AWS_REGION`` /
``AWS_DEFAULT_REGION``; an S3-compatible server, MinIO, Ceph, from ``AWS_ENDPOINT_URL_S3`` or
``AWS_ENDPOINT_URL``, e.g. ``http://127.0.0.1:9000``), any other scheme (``gs://``,
``hdfs://``, ``abfs://``) with :meth:`pyarrow.fs.FileSystem.from_uri`. pyarrow is already a
dependency, so no fsspec or s3fs.

**Inputs** are copied to a local temporary file before the existing readers read them
(:func:`download`): the object is streamed in :data:`CHUNK` pieces, so memory holds one chunk
whatever the log's size (the disk holds the log while it is converted; the copy is removed
after). A folder argument is a prefix, listed recursively for the suffixes a local folder is
searched for.

**Outputs** are written and verified locally (the same worker code as a local conversion), then
published (:func:`publish`): uploaded under a temporary key named as local temporaries are
(``.<name>.<pid>@<host>.<random>.tmp``, same prefix), the uploaded size checked against the
local file, then copied server-side to the final key (an object store's copy makes the object
appear whole or not at all) and the temporary key deleted. An interrupted run leaves no object
under a final name; temporary keys left by a killed worker are swept at the next run's start.

**The manifest** (``DIR/manifest.jsonl``) cannot be appended to on an object store: the driver
keeps its lines and publishes the whole object again (:class:`RemoteManifest`), at most every
:data:`MANIFEST_EVERY` seconds and at the end, including after an error or a signal.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any
from urllib.parse import urlsplit

from imupipe.pipeline.atomic import HOST_KEY, TEMP_NAME
from imupipe.pipeline.convert.options import URL, is_url, local_path  # noqa: F401 (remote.is_url)
from imupipe.pipeline.errors import ConfigError, ImupipeError
from imupipe.pipeline.signals import signals_deferred

CHUNK = 8 << 20
"""Bytes per read when copying an object (the memory a download or an upload holds)."""

MANIFEST_EVERY = 5.0
"""Seconds between two uploads of a remote manifest (and once at the end)."""

_FILESYSTEMS: dict[tuple[str, str], Any] = {}


class ObjectStoreError(ImupipeError):
    """The object store refuses an output (no permission, bucket gone, connection lost): every
    other log would fail the same way, so the conversion stops (``fatal``), as for a full or
    read-only output folder."""

    fatal = True


SCHEMES = ("s3", "s3a", "gs", "gcs")
"""The object stores imupipe opens (any other scheme is refused at once: pyarrow's other
filesystems may wait without end for credentials or a server)."""
GCS_RETRY_S = 10.0
"""Seconds a Google Cloud Storage request is retried before it fails (pyarrow's default retries
for 15 minutes, and looks for credentials on a metadata server first)."""


def check_url(value: str | os.PathLike[str], what: str = "") -> str:
    """``value`` (a URL) without its trailing slashes; ConfigError, one line, when its scheme is
    not an object store imupipe opens (:data:`SCHEMES`) or it names no bucket (``s3://``,
    ``s3:///x.mcap``)."""
    text = os.fspath(value)
    m = URL.match(text)
    label = f"{what} {text}".strip()
    if m is None:
        raise ConfigError(f"{label}: not a URL")
    scheme = m["scheme"].lower()
    if scheme not in SCHEMES:
        raise ConfigError(
            f"{label}: the scheme '{scheme}://' is not supported (s3://, gs://; or a local path)"
        )
    if not m["rest"].split("/", 1)[0]:
        raise ConfigError(f"{label}: names no bucket ({scheme}://BUCKET/PREFIX)")
    return text.rstrip("/")


def _s3_endpoint() -> dict[str, Any]:
    endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
    if not endpoint:
        return {}
    parts = urlsplit(endpoint if "://" in endpoint else "https://" + endpoint)
    return {"endpoint_override": parts.netloc, "scheme": parts.scheme or "https"}


def filesystem(url: str) -> tuple[Any, str]:
    """(the :mod:`pyarrow.fs` filesystem, the path in it) of ``url``; ConfigError (one line
    naming the URL) when the scheme is not supported or its settings are wrong."""
    import pyarrow.fs as pafs

    check_url(url)
    m = URL.match(url)
    assert m is not None  # check_url
    scheme = m["scheme"].lower()
    try:
        if scheme in ("gs", "gcs"):
            import datetime

            key = (scheme, "")
            if key not in _FILESYSTEMS:
                _FILESYSTEMS[key] = pafs.GcsFileSystem(
                    retry_time_limit=datetime.timedelta(seconds=GCS_RETRY_S)
                )
            return _FILESYSTEMS[key], m["rest"].rstrip("/")
        if scheme in ("s3", "s3a"):
            endpoint = _s3_endpoint()
            key = (scheme, repr(sorted(endpoint.items())))
            if key not in _FILESYSTEMS:
                # delayed open: a small object is sent with one PutObject on close
                _FILESYSTEMS[key] = pafs.S3FileSystem(allow_delayed_open=True, **endpoint)
            return _FILESYSTEMS[key], m["rest"].rstrip("/")
        fs, path = pafs.FileSystem.from_uri(url)
        return fs, path.rstrip("/")
    except (ValueError, OSError, TypeError) as exc:
        raise ConfigError(f"{url}: {' '.join(str(exc).split())}") from None


def join(url: str, rel: str) -> str:
    """``url`` + ``/`` + a relative POSIX path."""
    return url.rstrip("/") + "/" + rel.lstrip("/")


def _brief(exc: BaseException) -> str:
    """An object store's error in a few words (the SDK's messages are long)."""
    text = " ".join(str(exc).split())
    for marker in ("AWS Error ", "error: "):
        if marker in text:
            text = text.split(marker, 1)[1]
    for cut in (" (Request ID", " Learn more about", " error_info=", " The request was not sent"):
        text = text.split(cut)[0]
    return text.removeprefix("google::cloud::Status(").rstrip(".")


@dataclass
class Found:
    """A log found under a URL argument: its URL and its output name (relative, no suffix)."""

    url: str
    rel: PurePosixPath


def find_logs(url: str, suffixes: set[str], known: set[str]) -> list[Found]:
    """Every log under ``url``: the object itself, or the objects under the prefix whose suffix
    is in ``suffixes`` (names starting with a dot skipped). ConfigError, one line naming the URL:
    no such bucket, no such object or prefix, an object whose suffix names no log format
    (``known``)."""
    import pyarrow.fs as pafs

    fs, path = filesystem(url)
    bucket = path.split("/", 1)[0]
    try:
        info = fs.get_file_info(path)
        if info.type == pafs.FileType.NotFound and fs.get_file_info(bucket).type == (
            pafs.FileType.NotFound
        ):
            raise ConfigError(f"{url}: no such bucket '{bucket}'")
        if info.type == pafs.FileType.NotFound:
            raise ConfigError(f"{url}: no such object or prefix")
        if info.type == pafs.FileType.File:
            suffix = PurePosixPath(path).suffix.lower()
            if suffix not in known:
                raise ConfigError(
                    f"{url}: unknown log format '{suffix}' (expected one of "
                    f"{', '.join(sorted(known))})"
                )
            return [Found(url, PurePosixPath(PurePosixPath(path).stem))]
        listed = fs.get_file_info(pafs.FileSelector(path, recursive=True))
    except OSError as exc:
        raise ConfigError(f"{url}: cannot list: {_brief(exc)}") from None
    found = []
    for item in sorted(listed, key=lambda i: i.path):
        rel = PurePosixPath(item.path).relative_to(path)
        if (
            item.type == pafs.FileType.File
            and not any(part.startswith(".") for part in rel.parts)
            and rel.suffix.lower() in suffixes
        ):
            found.append(Found(join(url, rel.as_posix()), rel.with_suffix("")))
    return found


def object_size(url: str) -> int | None:
    """Bytes of an object, None when there is none."""
    import pyarrow.fs as pafs

    from imupipe.pipeline.errors import ReadError

    fs, path = filesystem(url)
    try:
        info = fs.get_file_info(path)
    except OSError as exc:
        raise ReadError(f"{url}: cannot read: {_brief(exc)}") from None
    return info.size if info.type == pafs.FileType.File else None


def download(url: str, dest: Path) -> int:
    """Copy the object ``url`` to the local file ``dest`` in :data:`CHUNK` pieces (memory: one
    chunk); returns its size. ReadError naming the URL when it cannot be read."""
    from imupipe.pipeline.errors import ReadError

    fs, path = filesystem(url)
    dest.parent.mkdir(parents=True, exist_ok=True)
    size = 0
    try:
        with fs.open_input_stream(path) as src, open(dest, "wb") as out:
            while chunk := src.read(CHUNK):
                out.write(chunk)
                size += len(chunk)
    except OSError as exc:
        if exc.filename is not None:  # the local copy: the worker's own disk
            raise
        raise ReadError(f"{url}: cannot read: {_brief(exc)}") from None
    return size


def _temp_key(url: str) -> str:
    import secrets  # an object store's upload only: not on a local command's path (issue 39)

    parent, _, name = url.rpartition("/")
    rand = "".join(secrets.choice("abcdefghijklmnopqrstuvwxyz0123456789_") for _ in range(8))
    return f"{parent}/.{name}.{os.getpid()}@{HOST_KEY}.{rand}.tmp"


def publish(items: list[tuple[Path, str]]) -> None:
    """Publish local files as objects: each uploaded under a temporary key, its size checked,
    then all copied to their final keys in order (the caller puts the one that marks the log
    done last) and the temporary keys deleted. On any failure the temporary keys are deleted and
    no final key is touched until every upload is complete and checked; ObjectStoreError (one
    line naming the URL) when the store refuses."""
    staged: list[tuple[Any, str, str]] = []
    url = ""
    try:
        for local, url in items:
            fs, final = filesystem(url)
            tmp = filesystem(_temp_key(url))[1]
            staged.append((fs, tmp, final))
            with open(local, "rb") as src, fs.open_output_stream(tmp) as out:
                while chunk := src.read(CHUNK):
                    out.write(chunk)
            got, want = fs.get_file_info(tmp).size, local.stat().st_size
            if got != want:
                raise ObjectStoreError(f"{url}: uploaded {got} bytes of {want}; not published")
        with signals_deferred():  # the copies and the clean-up are not cut in two
            try:
                for (fs, tmp, final), (_, target) in zip(staged, items, strict=True):
                    url = target  # named by the error, if the copy fails
                    fs.copy_file(tmp, final)
            finally:
                _delete(staged)
    except OSError as exc:
        if exc.filename is not None:
            raise
        raise ObjectStoreError(f"{url}: cannot write: {_brief(exc)}") from None
    finally:
        _delete(staged)


def _delete(staged: list[tuple[Any, str, str]]) -> None:
    """Delete the temporary keys of :func:`publish` (those already gone are skipped)."""
    while staged:
        fs, tmp, _ = staged.pop()
        with contextlib.suppress(OSError):
            fs.delete_file(tmp)


def probe(url: str) -> None:
    """ConfigError (one line) unless an object can be written under ``url`` (the bucket exists,
    the credentials may write)."""
    import pyarrow.fs as pafs

    fs, path = filesystem(url)
    bucket = path.split("/", 1)[0]
    key = f"{path}/.probe.{os.getpid()}@{HOST_KEY}.tmp"
    try:
        if fs.get_file_info(bucket).type == pafs.FileType.NotFound:
            raise ConfigError(f"--out {url}: no such bucket '{bucket}'")
        with fs.open_output_stream(key) as out:
            out.write(b"")
        fs.delete_file(key)
    except OSError as exc:
        raise ConfigError(f"--out {url}: cannot write: {_brief(exc)}") from None


def remove_stale_temps(url: str) -> list[str]:
    """Delete the temporary keys (names of :data:`~imupipe.pipeline.atomic.TEMP_NAME`) directly
    under the prefix ``url`` (not below): called by the driver before any worker starts and
    after its workers are stopped, when every one of them is a leftover (one conversion at a
    time writes into ``DIR``; a worker still finishing has its copy fail on the missing key, and
    publishes nothing). Returns the URLs deleted."""
    import pyarrow.fs as pafs

    fs, path = filesystem(url)
    removed = []
    try:
        listed = fs.get_file_info(pafs.FileSelector(path, allow_not_found=True))
    except OSError:
        return []
    for item in listed:
        name = PurePosixPath(item.path).name
        if item.type == pafs.FileType.File and TEMP_NAME.match(name):
            with contextlib.suppress(OSError):
                fs.delete_file(item.path)
                removed.append(join(url, name))
    return removed


SUMMARY_MAX = 64 << 20
"""The most bytes of an MCAP's summary section read in one request (a larger one is read as it
is parsed)."""


class _Tail:
    """A seekable view of a remote file that holds its last bytes (the MCAP summary section,
    fetched with one ranged read) and reads anything before them as asked: the ``mcap``
    reader parses the summary record by record, which would otherwise be one request per
    record."""

    def __init__(self, fh: Any, size: int) -> None:
        self.fh, self.size, self.pos = fh, size, 0
        footer = 8 + 29  # magic and the footer record (opcode, length, three fields)
        start = size
        if size >= footer:
            fh.seek(size - footer)
            tail = fh.read(footer)
            summary_start = int.from_bytes(tail[9:17], "little")
            if 0 < summary_start < size and size - summary_start <= SUMMARY_MAX:
                start = summary_start
        fh.seek(start)
        self.start, self.buf = start, fh.read(size - start)

    def seek(self, offset: int, whence: int = 0) -> int:
        base = {0: 0, 1: self.pos, 2: self.size}[whence]
        self.pos = base + offset
        return self.pos

    def tell(self) -> int:
        return self.pos

    def seekable(self) -> bool:
        return True

    def readable(self) -> bool:
        return True

    def read(self, n: int = -1) -> bytes:
        n = self.size - self.pos if n is None or n < 0 else n
        if self.pos >= self.start:
            data = self.buf[self.pos - self.start : self.pos - self.start + n]
        else:
            self.fh.seek(self.pos)
            data = self.fh.read(n)
        self.pos += len(data)
        return data


def read_mcap_summary(url: str) -> Any:
    """:func:`~imupipe.pipeline.convert.verify.mcap_summary` of an object (its summary section
    fetched with one ranged read, :class:`_Tail`); None when there is no such object."""
    from imupipe.pipeline.convert.verify import summary_of

    fs, path = filesystem(url)
    size = object_size(url)
    if size is None:
        return None
    with fs.open_input_file(path) as fh:
        return summary_of(_Tail(fh, size))


class RemoteManifest:
    """``DIR/manifest.jsonl`` on an object store (driver only): the lines already there are kept,
    each new line is added in memory and the whole object is published again (through a
    temporary key and a copy: it appears whole) at most every :data:`MANIFEST_EVERY` seconds
    and by :meth:`flush`. A run killed outright may lose the lines of its last seconds; the
    next run finds those logs' outputs and records them as skipped."""

    def __init__(self, url: str) -> None:
        from imupipe.pipeline.convert.manifest import MANIFEST_NAME

        self.path = join(url, MANIFEST_NAME)
        fs, key = filesystem(self.path)
        self._data = b""
        if object_size(self.path) is not None:
            try:
                with fs.open_input_stream(key) as src:
                    self._data = src.read()
            except OSError as exc:
                raise ObjectStoreError(f"{self.path}: cannot read: {_brief(exc)}") from None
            if self._data and not self._data.endswith(b"\n"):  # a line cut short: dropped
                self._data = self._data[: self._data.rfind(b"\n") + 1]
        self._dirty = False
        self._last = 0.0

    def append(self, record: Mapping[str, Any]) -> None:
        from imupipe.pipeline.convert.manifest import line_bytes

        self._data += line_bytes(record)
        self._dirty = True
        if time.monotonic() - self._last >= MANIFEST_EVERY:
            self.flush()

    def flush(self) -> None:
        """Publish the manifest if a line was added since the last upload."""
        if not self._dirty:
            return
        import tempfile

        with tempfile.TemporaryDirectory(prefix="imupipe-manifest-") as tmp:
            local = Path(tmp) / "manifest.jsonl"
            local.write_bytes(self._data)
            publish([(local, self.path)])
        self._dirty = False
        self._last = time.monotonic()

    def lines(self) -> bytes:
        return self._data
