"""One input request at a time, and what can go wrong with it: a local file's bytes, a remote
object's GET, a remote folder's listing, each failure as a one-line ``SourceError`` naming the path.

Nothing here keeps state or counts: :class:`sources.reader.Reader` makes every request of a run
through these functions and counts them. A remote file is one GET of the whole object, or a ranged
GET of its head (:func:`get_remote`; on S3 conditional on the folder listing's ETag and checked
against its size), never a HEAD first.
"""

from __future__ import annotations

from dataclasses import dataclass

from upath import UPath

from ncore_convert.errors import SourceError
from ncore_convert.paths import is_local


@dataclass(frozen=True)
class ObjectInfo:
    """One object as its folder's listing gave it: size in bytes, and the ETag (None where the
    store gives none)."""

    size: int
    etag: str | None = None


def key(path: UPath) -> str:
    """The name a listing files an object under: its protocol and path."""
    return f"{path.protocol}://{path.path}" if not is_local(path) else path.path


def unreadable(path: object, err: OSError) -> SourceError:
    """The SourceError for a file that could not be read: missing, or refused with the OS's reason."""
    if isinstance(err, FileNotFoundError):
        return SourceError(path, "file not found")
    return SourceError(path, f"unreadable ({err.strerror or type(err).__name__})")


def checked(path: UPath, data: bytes, info: ObjectInfo | None) -> bytes:
    """``data``, unless its length differs from the listing's (SourceError naming ``path``)."""
    if info is not None and len(data) != info.size:
        raise SourceError(path, f"object is {len(data)} bytes, its listing says {info.size} (short, or changed)")
    return data


def read_local(path: UPath, max_bytes: int = -1) -> bytes:
    """A local file's bytes (its first ``max_bytes`` only, if given); SourceError naming it if it is
    missing or unreadable. Plain ``open`` is about 3x cheaper per file than going through fsspec."""
    try:
        with open(path.path, "rb") as f:
            return f.read(max_bytes)
    except OSError as err:
        raise unreadable(path, err) from None


def remote_error(path: UPath, err: Exception) -> SourceError:
    """The one-line SourceError for a failed remote request (an ETag that no longer matches, a
    missing object, a refusal)."""
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
    return checked(path, data, info) if max_bytes < 0 else data


def get_remote_sync(path: UPath, info: ObjectInfo | None, max_bytes: int = -1) -> bytes:
    """:func:`get_remote` for a store without an async interface (one request, same checks)."""
    try:
        data = path.fs.cat_file(path.path) if max_bytes < 0 else path.fs.cat_file(path.path, 0, max_bytes)
    except Exception as err:  # noqa: BLE001 - every failure becomes the file's one-line error
        raise remote_error(path, err) from None
    return checked(path, data, info) if max_bytes < 0 else data


def list_remote(directory: UPath) -> list[dict]:
    """The entries directly in a remote folder, from one listing (the store's pages of 1,000 keys
    followed; never a cached one); [] for a folder that does not exist."""
    try:
        return directory.fs.ls(directory.path, detail=True, refresh=True)
    except FileNotFoundError:
        return []


def entry_info(entry: dict) -> ObjectInfo:
    """A listing entry's size and ETag."""
    return ObjectInfo(int(entry.get("size") or 0), entry.get("ETag") or entry.get("etag"))
