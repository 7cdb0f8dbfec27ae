"""Source files as bytes: reading with clear causes (``errors.SourceError``), folder listings with
safe names, and cheap completeness checks of encoded images.

A remote file (s3://, ...) is one request: a GET of the whole object, or a ranged GET of its head
(:func:`get_remote`; on S3 conditional on the folder listing's ETag and checked against its size),
never a HEAD first. Each process counts its remote GETs and bytes (:data:`COUNTS`);
:mod:`sources.objects` fetches many ahead and keeps what a log reads again.

Images are stored byte-identical, so the converter never decodes them; the checks catch the damage
that interrupted downloads cause (a file cut short, or not an image at all) from the first and last
bytes only.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import fsspec.asyn
from upath import UPath

from ncore_convert.contract import SAFE_NAME
from ncore_convert.errors import SourceError
from ncore_convert.storage import is_local


def check_safe_names(path: object, names: list[str], what: str) -> None:
    """SourceError naming ``path`` if a name could escape, or hide in, the output folder."""
    bad = [name for name in names if not SAFE_NAME.match(name)]
    if bad:
        raise SourceError(path, f"{what} {bad[0]!r} is not a safe name (letters, digits, '_', '-', '.'; 128 at most)")


def list_folders(directory: UPath, what: str) -> list[str]:
    """The sorted names of the visible folders in ``directory`` (logs, scenarios), each checked to
    be a safe name (SourceError naming ``directory`` otherwise)."""
    names = sorted(p.name for p in directory.iterdir() if p.is_dir() and not p.name.startswith("."))
    check_safe_names(directory, names, what)
    return names


def require_folder(path: UPath, noun: str) -> None:
    """SourceError unless ``path`` is a folder with something in it (``noun``: "log directory", ...)."""
    if not path.is_dir():
        raise SourceError(path, f"{noun} not found")
    if not any(path.iterdir()):
        raise SourceError(path, f"empty {noun} (an interrupted download?)")


def unreadable(path: object, err: OSError) -> SourceError:
    """The SourceError for a file that could not be read: missing, or refused with the OS's reason."""
    if isinstance(err, FileNotFoundError):
        return SourceError(path, "file not found")
    return SourceError(path, f"unreadable ({err.strerror or type(err).__name__})")


def read_bytes(path: UPath, max_bytes: int = -1) -> bytes:
    """A file's bytes (its first ``max_bytes`` only, if given); SourceError naming it if it is
    missing or unreadable. A remote file is one GET (:func:`get_remote`), never a HEAD first."""
    if not is_local(path):
        if getattr(path.fs, "async_impl", False):
            return fsspec.asyn.sync(path.fs.loop, get_remote, path, None, max_bytes)
        try:
            data = path.fs.cat_file(path.path) if max_bytes < 0 else path.fs.cat_file(path.path, 0, max_bytes)
        except Exception as err:  # noqa: BLE001 - every failure becomes the file's one-line error
            raise remote_error(path, err) from None
        count_fetch(path, data)
        return data
    try:
        with open(path.path, "rb") as f:  # plain open is ~3x cheaper per file than going through fsspec
            return f.read(max_bytes)
    except OSError as err:
        raise unreadable(path, err) from None


# ----------------------------------------------------------------------------------------------
# Remote objects: one request each, counted
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ObjectInfo:
    """One object as its folder's listing gave it: size in bytes, and the ETag (None where the
    store gives none)."""

    size: int
    etag: str | None = None


@dataclass
class Counts:
    """Remote fetches of this process: requests (GETs, LISTs), bytes, and files fetched again."""

    gets: int = 0
    lists: int = 0
    bytes: int = 0
    refetched: int = 0
    spooled: int = 0  #: files written to the spool
    spool_hits: int = 0  #: files read from the spool instead of fetched
    not_kept: int = 0  #: files a later job reads again, not spooled (the spool was full): fetched again


COUNTS = Counts()

_seen: set[str] = set()  #: objects fetched by this process (a second fetch counts in ``refetched``)
_lock = threading.Lock()


def key(path: UPath) -> str:
    """The name a listing files an object under: its protocol and path."""
    return f"{path.protocol}://{path.path}" if not is_local(path) else path.path


def checked(path: UPath, data: bytes, info: ObjectInfo | None) -> bytes:
    if info is not None and len(data) != info.size:
        raise SourceError(path, f"object is {len(data)} bytes, its listing says {info.size} (short, or changed)")
    return data


def count_fetch(path: UPath, data: bytes) -> None:
    with _lock:
        COUNTS.gets += 1
        COUNTS.bytes += len(data)
        name = key(path)
        if name in _seen:
            COUNTS.refetched += 1
        _seen.add(name)


def remote_error(path: UPath, err: Exception) -> SourceError:
    response = getattr(err.__cause__, "response", None) or getattr(err, "response", None) or {}
    code = response.get("Error", {}).get("Code")
    status = response.get("ResponseMetadata", {}).get("HTTPStatusCode")
    if code == "PreconditionFailed" or status == 412:
        return SourceError(path, "object changed since its folder was listed (ETag differs)")
    if isinstance(err, OSError):
        return unreadable(path, err)
    return SourceError(path, f"unreadable ({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''})")


async def get_remote(path: UPath, info: ObjectInfo | None, max_bytes: int = -1) -> bytes:
    """One GET of the whole object, or of its first ``max_bytes`` (S3: conditional on the listing's
    ETag ``info``, and checked against its size; never s3fs's ``_cat_file``, which asks for the
    size first, a HEAD, when it may split a large object)."""
    fs = path.fs
    try:
        if hasattr(fs, "_call_s3"):
            bucket, name, version = fs.split_path(path.path)
            condition = {"IfMatch": info.etag} if info is not None and info.etag else {}
            version_kw = {"VersionId": version} if version else {}
            part = {"Range": f"bytes=0-{max_bytes - 1}"} if max_bytes >= 0 else {}
            response = await fs._call_s3("get_object", Bucket=bucket, Key=name, **condition, **version_kw, **part)
            try:
                data = await response["Body"].read()
            finally:
                response["Body"].close()
        else:
            data = await fs._cat_file(path.path, **({"start": 0, "end": max_bytes} if max_bytes >= 0 else {}))
    except Exception as err:  # noqa: BLE001 - every failure becomes the object's one-line error
        raise remote_error(path, err) from None
    count_fetch(path, data)
    return checked(path, data, info) if max_bytes < 0 else data


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_IEND = b"IEND\xaeB`\x82"  #: the IEND chunk's type and CRC, the last 8 bytes of a PNG
_JPEG_SOI = b"\xff\xd8"
_JPEG_EOI = b"\xff\xd9"
_TAIL_BYTES = 1024  #: encoders may pad after the end marker; a marker this close to the end counts


def jpeg_defect(data: bytes) -> str | None:
    """Why ``data`` is not a complete JPEG (missing start or end-of-image marker), or None."""
    if not data.startswith(_JPEG_SOI):
        return "not a JPEG file (missing SOI marker)"
    if data.rfind(_JPEG_EOI, max(2, len(data) - _TAIL_BYTES)) < 0:
        return "truncated JPEG (no EOI marker at the end)"
    return None


def png_defect(data: bytes) -> str | None:
    """Why ``data`` is not a complete PNG (missing signature or IEND chunk), or None."""
    if not data.startswith(PNG_SIGNATURE):
        return "not a PNG file (missing signature)"
    if data.rfind(_PNG_IEND, len(PNG_SIGNATURE), len(data)) < max(len(PNG_SIGNATURE), len(data) - _TAIL_BYTES):
        return "truncated PNG (no IEND chunk at the end)"
    return None
